"""The iPhone 4s recordings of the smartphone attitude benchmark (Michel et al., PerCom 2017) in the
generic format (``../shared/datasets/phones/iphone4s``; conversion and caveats in its README): read by the
generic loader, named as the device (``data=iphone4s``, conf/data/iphone4s.yaml: the split by user)."""
from .generic import list_recordings, load_recording as _load

__all__ = ["list_recordings", "load_recording"]


def load_recording(root, name: str):
    seq = _load(root, name)
    seq.meta["dataset"] = "iphone4s"
    return seq
