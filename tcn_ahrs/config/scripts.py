"""The other scripts' configs: evaluate, compare, benchmark, export, inspect_data, reproduce
(top-level keys; ``data:`` / ``paper:`` are their own schemas, ``hydra:`` Hydra's)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional


@dataclass
class EvaluateConfig:
    """conf/evaluate.yaml: a checkpoint (+ Raw IMU and ``baselines``) through the runner."""
    run_dir: Optional[str] = None   # a training run: write into its eval/ subfolder
    ckpt: Optional[str] = None      # null: the backbone with VQF's defaults (device-checked); general9 etc.: shipped by name
    out: Optional[str] = None       # null: Hydra's run dir runs/eval/<date_time>
    overwrite: bool = False         # an out= holding an earlier run's files is refused unless true
    baselines: List[str] = field(default_factory=list)
    plugins: List[str] = field(default_factory=list)  # modules registering more methods
    name: str = "Learned AHRS"
    reanchor: Optional[int] = None  # open loop: restart the ECF every N samples (null: paper)
    other_rate: str = "backbone"    # residual model at another rate: backbone | model
    device: str = "cpu"
    threads: Optional[int] = None
    plots: bool = True
    trajectories: bool = True
    align: str = "protocol"      # the yardstick (tcn_ahrs.metrics); or heading | first | none
    # the offline device check (tcn_ahrs.device_check, no ground truth): each recording's gyro bias at
    # rest, read from the whole recording, subtracted before every method; auto: with the general models
    # and a model trained on checked recordings (train.device_check); the default (no ckpt) checks
    # causally inside its filter (kernels/backbone.py: rest_check) and every method gets raw readings
    device_check: str = "auto"   # auto | offline (old name: true) | false


@dataclass
class CompareConfig:
    """conf/compare.yaml: every method, tuned on training recordings, through the runner."""
    methods: Optional[List[str]] = None  # null: every registered raw + classical method
    plugins: List[str] = field(default_factory=list)
    peers: bool = False                  # add all PyPI peers (skipped when not installed)
    both_axes: bool = True               # 9-axis data: also the 6D column of each method
    variants: List[str] = field(default_factory=lambda: ["default", "tuned"])
    tune: bool = False
    tune_split: str = "train"            # train | trainval
    tune_data: Optional[str] = None      # tune on another dataset's training recordings
    tune_root: Optional[str] = None
    tune_max_seconds_per_recording: Optional[float] = 60.0
    tune_lead_seconds: Optional[float] = 10.0
    tune_recordings: Optional[int] = None
    tune_max_batch: int = 128
    ckpts: Optional[Dict[str, str]] = None           # {label: path}
    on_calibrated: Optional[Dict[str, str]] = None   # {label: checkpoint}
    ablation_ckpts: Optional[Dict[str, str]] = None  # Table 3 layout
    out: Optional[str] = None
    plots: bool = False
    trajectories: bool = False
    align: str = "protocol"      # the yardstick (tcn_ahrs.metrics); or heading | first | none
    reanchor: Optional[int] = None
    device: str = "cpu"
    threads: Optional[int] = None
    verbose: bool = False


@dataclass
class TransferSection:
    """benchmark ``transfer:`` (tcn_ahrs.experiments.transfer, the cross-dataset matrix)."""
    ckpts: Optional[Dict[str, str]] = None  # null: every checkpoints/*.ckpt and *.json
    datasets: Optional[List[str]] = None
    baselines: Optional[List[str]] = None
    rates: Optional[List[float]] = None     # Hz: each checkpoint's cells resampled to these rates


@dataclass
class LodoSection:
    """benchmark ``lodo:`` (tcn_ahrs.experiments.lodo, leave one dataset out)."""
    datasets: Optional[List[str]] = None
    experiment: str = "general6_residual"
    overrides: List[str] = field(default_factory=list)
    runs: str = "runs/lodo"
    train: bool = True
    reselect: bool = False
    nested: str = "runs/nested"
    baselines: Optional[List[str]] = None
    device_check: bool = True       # every method on the recordings with their rest bias subtracted (as evaluate)


@dataclass
class FinetuneSection:
    """benchmark ``finetune:`` (tcn_ahrs.experiments.finetune)."""
    datasets: Optional[List[str]] = None
    k: int = 2
    modes: List[str] = field(default_factory=lambda: ["gt", "self"])
    overrides: List[str] = field(default_factory=list)
    lodo_runs: str = "runs/lodo"
    runs: str = "runs/finetune"
    baselines: Optional[List[str]] = None
    device_check: bool = True       # every method (and the fine-tuning) on device-checked recordings


@dataclass
class FaultsSection:
    """benchmark ``faults:`` (tcn_ahrs.bench.faults)."""
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])  # one simulated walk per seed
    ckpt: Optional[str] = "checkpoints/general9_residual.ckpt"             # the learned column (null: none)


@dataclass
class DevicesSection:
    """benchmark ``devices:`` (tcn_ahrs.experiments.devices)."""
    datasets: Optional[List[str]] = None   # conf/data names; null: every real dataset
    models: Optional[List[str]] = None     # shipped model names; null: every shipped model
    quick: bool = False                    # the quick subset (the README's test command)


@dataclass
class BenchmarkConfig(CompareConfig):
    """conf/benchmark.yaml: compare.yaml's keys + the modes' own (``speed:``: :mod:`.speed`)."""
    mode: str = "accuracy"           # accuracy | speed | transfer | lodo | finetune | faults | devices
    peers: bool = True
    ckpt: Optional[str] = None       # a learned checkpoint, column ckpt_label
    ckpt_label: str = "Proposed"
    transfer: TransferSection = field(default_factory=TransferSection)
    lodo: LodoSection = field(default_factory=LodoSection)
    finetune: FinetuneSection = field(default_factory=FinetuneSection)
    faults: FaultsSection = field(default_factory=FaultsSection)
    devices: DevicesSection = field(default_factory=DevicesSection)
    quick: bool = False              # speed mode only
    speed: Dict[str, Any] = field(default_factory=dict)  # checked by tcn_ahrs.bench.resolve_config


@dataclass
class ExportConfig:
    """conf/export.yaml: a checkpoint as a deployment file."""
    ckpt: Optional[str] = None     # checkpoint written by scripts/train.py (required)
    out: Optional[str] = None      # output file (required): FILE.pt | FILE.onnx | FILE.pt2 | NAME.c (+ NAME.h)
    format: str = "torchscript"    # torchscript | onnx | export (torch.export) | c (C99): the last three residual models only
    mode: str = "both"             # batch | streaming | both (torchscript)
    rate: Optional[float] = None   # Hz, recorded when the checkpoint lacks it
    overwrite: bool = False
    net_dtype: str = "float32"     # float32 | float64


@dataclass
class InspectDataConfig:
    """conf/inspect_data.yaml: a per-recording summary of a data split."""
    min_gap_s: float = 0.05        # ground-truth gaps longer than this are counted
    json: Optional[str] = None     # also write the summaries as JSON


@dataclass
class ReproduceConfig:
    """conf/reproduce.yaml's top level (``paper:``: :mod:`.papers`)."""
    out: Optional[str] = None
