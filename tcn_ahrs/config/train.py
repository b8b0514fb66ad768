"""``conf/train.yaml`` (``train:``, ``eval:``, its top level) and ``conf/crossval.yaml``.

The defaults are the simulator run's (``python scripts/train.py``); real-data recipes override
them in conf/experiment/*.yaml."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Dict, List, Optional, Tuple


def _num(default, low: float, low_ok: bool = True, high: Optional[float] = None):
    """A numeric field with its admissible range: >= low (> low when not ``low_ok``), < high."""
    return field(default=default, metadata={"range": (low, low_ok, high)})


@dataclass
class AugmentConfig:
    """``train.augment``: another device (open loop / residual models)."""
    rate_hz: Optional[List[float]] = None  # [low, high] Hz: each window resampled to a log-uniform random rate
    jitter: float = _num(0.0, 0.0, True, 0.49)  # < 0.5: irregular sampling, every step moved by up to +-jitter/2
    rotate: bool = False      # the sensor mounted in a random orientation per window
    gyro_bias: float = _num(0.0, 0.0)  # rad/s: std of a constant gyro offset per window
    scale: float = _num(0.0, 0.0)  # std of a per-axis gyro/accelerometer scale error


@dataclass
class NoiseConfig:
    """``train.noise``: Gaussian white-noise augmentation of the raw readings."""
    gyro: float = _num(0.001, 0.0)       # rad/s
    acc: float = _num(0.01, 0.0)         # m/s^2
    mag: float = _num(0.1, 0.0)          # uT
    gyro_bias: float = _num(0.005, 0.0)  # closed loop: rad/s, a constant random gyro offset per stream


@dataclass
class TrainConfig:
    """``train:``."""
    window: int = _num(500, 2)             # samples per training window (closed loop: per chained chunk)
    stride: int = _num(200, 1)             # spacing of admissible window starts (one epoch = all of them)
    batch_size: int = _num(16, 1)
    epochs: int = _num(14, 1)              # simulator default; real data: experiment=<name>_cl
    lr: float = _num(0.003, 0.0, False)  # AdamW (real-data configs: 1e-3; the paper: 0.01)
    stream_chunks: int = _num(8, 1)        # closed loop: chunks a stream runs before it restarts
    attitude_delta: float = _num(0.01, 0.0, False)  # closed loop: Huber delta of the attitude loss, rad
    ema_decay: float = _num(0.98, 0.0, True, 1.0)  # weight average for validation, selection, release (0: off)
    init_gyro_bias: bool = True   # closed loop: gyro error term starts at the mean gyro at rest
    tune_backbone: bool = True    # model=residual: the backbone's knobs chosen on the training recordings
    tune_criterion: str = "aae"   # aae | never_worse
    select_knobs: bool = True     # model=residual: inference knobs chosen on the validation recordings
    knob_grid: Optional[Dict[str, Any]] = None  # that choice's grid; null: knobs.RESIDUAL_KNOB_GRID
    knob_rule: str = "both"       # both | either
    all_recordings: bool = False  # train on every training recording, whole, nothing held out
    device_check: bool = False    # each recording's gyro bias at rest subtracted first (tcn_ahrs.device_check);
                                  # stored in the checkpoint, so evaluate does the same before it
    keep_if_not_better: bool = True  # fine-tuning (init=): ships only if better on held-out evidence
                                     # (tcn_ahrs.training.adaptation), else the starting model ships
    adopt_on: str = "recordings"  # that evidence: recordings (each of >= 2 left out of a fine-tuning of its own,
                                  # scored whole: cross-fitted) | parts (the later halves of the validation parts)
    weight_decay: float = _num(0.1, 0.0)
    loss_js: List[int] = field(default_factory=lambda: [16, 32])  # open loop: increment lengths (Eq. 28)
    huber_delta: float = _num(0.005, 0.0, False)    # rad (Eq. 27)
    supervision: str = "gt"       # gt: motion capture | self: no ground truth
    balance: bool = False         # as many windows from every dataset part per epoch
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    monitor: str = "val/aae_deg"  # checkpoint selection: val/aae_deg or val/loss
    max_time: Any = "00:00:04:00"  # safety cap: "DD:HH:MM:SS" (or Lightning's {hours: 1}); null: none
    limit_train_batches: Optional[float] = None


def numeric_ranges(schema) -> Dict[str, Tuple[type, float, bool, Optional[float]]]:
    """(type, lower bound, lower bound included, upper bound exclusive) of a schema's ranged fields."""
    kinds = {"int": int, "float": float}
    return {f.name: (kinds[str(getattr(f.type, "__name__", f.type))], *f.metadata["range"])
            for f in fields(schema) if "range" in f.metadata}


@dataclass
class EvalSection:
    """``eval:``: the held-out evaluation after training."""
    enabled: bool = True
    split: str = "test"
    # raw is always there; VQF's structure and every classical filter, the best one marked
    baselines: List[str] = field(default_factory=lambda: ["backbone", "vqf", "ecf", "mahony", "madgwick", "eskf"])
    name: str = "Learned AHRS"
    plots: bool = True
    trajectories: bool = True


@dataclass
class TrainScriptConfig:
    """train.yaml's top level (groups ``data``, ``model``, ``trainer``, ``callbacks``, ``logger``
    are checked by their own schemas / instantiation)."""
    seed: int = 0
    threads: Optional[int] = 2      # torch.set_num_threads; null: torch's default
    resume: bool = False            # continue from this run dir's (or the newest sibling's) last.ckpt
    ckpt_path: Optional[str] = None  # continue from this checkpoint
    init: Optional[str] = None      # fine-tuning: start from this checkpoint
    run_dir: Optional[str] = None   # null: Hydra's run dir
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalSection = field(default_factory=EvalSection)


#: train.yaml's config groups (each checked by its own schema or by instantiation)
TRAIN_GROUPS = ("data", "model", "trainer", "callbacks", "logger", "hydra")


@dataclass
class CrossvalSection:
    """``crossval:`` (conf/crossval.yaml = train.yaml + this section)."""
    folds: Optional[List[int]] = None  # fold indices to run (null: all of data.folds)
    methods: List[str] = field(default_factory=lambda: ["raw", "backbone", "ecf", "mahony", "madgwick", "eskf",
                                                        "robust_eskf"])
    peers: bool = True                 # + the PyPI peers when installed
    tune: bool = False                 # also tune the classical filters on the fold's training recordings
    tune_max_seconds_per_recording: Optional[float] = 60.0
    inner: str = "auto"                # fold | split | auto
    reselect: bool = False             # residual model: knobs chosen again on each fold's inner set
    retrain: bool = False              # train again even where a fold's checkpoint exists
    out: Optional[str] = None          # null: runs/crossval/<data>_<model.variant>
    label: str = "Learned"             # column name of the learned model
    untrained: Optional[List[Dict[str, Any]]] = None  # model.closed_loop overrides: score the untrained loop


@dataclass
class LearnRecipe:
    """One learned recipe of the search (``conf/search/learn/<recipe>.yaml``)."""
    name: str = ""                                       # the candidate's name in the search's tables
    overrides: List[str] = field(default_factory=list)   # conf/train.yaml overrides; {axes}, {shipped} filled in


@dataclass
class SearchSection:
    """``search:`` (conf/search.yaml = train.yaml + this section; tcn_ahrs.experiments.search)."""
    folds: Optional[List[int]] = None  # outer fold indices to run (null: all of data.folds)
    inner: str = "auto"                # inner validation: folds (every other fold in turn) | fold | split | auto
    families: List[str] = field(default_factory=lambda: ["strapdown", "ecf", "mahony", "madgwick", "backbone"])
    calibrations: List[str] = field(default_factory=lambda: ["none", "gyro_bias", "full", "device_check"])
    learn: List[str] = field(default_factory=lambda: ["finetune", "residual", "closed_loop"])  # learned recipes
                                       # trained inside the folds (tcn_ahrs.experiments.search.learn.RECIPES)
    budget_minutes: Optional[float] = 60.0  # the whole search's compute; the trainings share what the classical part leaves
    # {axes: folder} of the general models trained without each dataset (tcn-ahrs benchmark lodo): a recipe
    # whose shipped starting model saw the search's data starts from <folder>/<data> instead (else left out)
    lodo_runs: Dict[str, str] = field(default_factory=lambda: {"6": "runs/lodo", "9": "runs/lodo9"})
    learned: Optional[Dict[str, str]] = None  # {family: crossval folder}: its fold checkpoints are candidates
    learned_checkpoint: str = "last"   # last (end of schedule: unbiased on the inner fold) | selected
    trials: int = 40                   # Optuna trials per family x calibration and fold (the defaults first)
    tune_seconds: Optional[float] = None  # tune on clips this long of each recording (null: whole)
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])   # sampler seeds: every fold over each
    tie_margin: float = 0.02           # a simpler family within 2 % of the best inner-validation AAE wins
    incl_margin: float = 0.05          # deg: no candidate with an inclination worse than the best by more
    out: Optional[str] = None          # null: runs/search/<data>_<axes>


@dataclass
class SearchConfig(TrainScriptConfig):
    search: SearchSection = field(default_factory=SearchSection)


@dataclass
class CrossvalConfig(TrainScriptConfig):
    crossval: CrossvalSection = field(default_factory=CrossvalSection)
