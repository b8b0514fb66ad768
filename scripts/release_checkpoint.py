"""Slim a training checkpoint for release (weights + model record, no optimiser state).

    python scripts/release_checkpoint.py SRC.ckpt DST.ckpt
"""
import hashlib
import sys
from pathlib import Path

from tcn_ahrs.checkpoint import release_checkpoint

if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    meta = release_checkpoint(sys.argv[1], sys.argv[2])
    data = Path(sys.argv[2]).read_bytes()
    print(f"{sys.argv[2]}: {len(data) / 1e6:.2f} MB, sha256 {hashlib.sha256(data).hexdigest()}, "
          f"variant {meta['model'].get('variant')}, axes {meta['layout']['axes']}")
