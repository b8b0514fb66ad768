"""``data:`` — conf/data/<name>.yaml. Each dataset has its own keys, so this is looser than the
other schemas: the keys every data config has (:class:`DataCommon`), the recording-list datasets'
(:class:`RecordingsData`: broad, euroc, tumvi, oxiod, generic), and the extras of the rosbag
reader, the simulator and the multi-dataset configs. A new ``conf/data/<name>.yaml`` of a
recording-list dataset needs no new schema; one with keys of its own adds its class to
:data:`DATA_SCHEMAS`. A data config's keys are checked against its schema whenever it is loaded
(:func:`tcn_ahrs.datasets.check_data_keys`), its files' values by tests/test_config_schema.py."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from omegaconf import MISSING


@dataclass
class DataCommon:
    name: str = MISSING          # module name in tcn_ahrs.datasets (or an importable module)
    split: str = "train"         # train | val | trainval | test | all
    axes: int = 9                # 9 or 6 (6 drops the magnetometer)


@dataclass
class RecordingsData(DataCommon):
    """A folder of recordings, splits as lists of their names."""
    root: str = MISSING          # relative to the working directory (falls back to the repo root)
    train: List[str] = field(default_factory=list)   # training recordings: first part trains, the rest validates
    test: List[str] = field(default_factory=list)
    train_part: Dict[str, float] = field(default_factory=lambda: {"fraction": 0.7})  # {seconds: s} or {fraction: f}
    fold: Optional[int] = None   # leave-recordings-out: index into folds
    folds: List[List[str]] = field(default_factory=list)


@dataclass
class RosbagTopics:
    imu: str = "/imu/data"       # sensor_msgs/Imu
    mag: Optional[str] = None    # sensor_msgs/MagneticField (Tesla)
    pose: Optional[str] = None   # PoseStamped / PoseWithCovarianceStamped / Odometry ground truth


@dataclass
class RosbagData(RecordingsData):
    topics: RosbagTopics = field(default_factory=RosbagTopics)
    declare: Dict[str, Any] = field(default_factory=dict)  # generic-format declarations


@dataclass
class SimulatedSplit:
    count: int = MISSING
    duration: float = MISSING       # s
    seed_offset: int = MISSING
    profiles: List[str] = MISSING
    error_params: Dict[str, Any] = field(default_factory=dict)


@dataclass
class SimulatedData(DataCommon):
    """The built-in simulator (tcn_ahrs/datasets/simulate/)."""
    rate: float = 100.0             # Hz
    device_seed: int = 7            # the simulated sensor (same in every split)
    error_params: Dict[str, Any] = field(default_factory=dict)
    splits: Dict[str, SimulatedSplit] = field(default_factory=dict)


@dataclass
class GeneralData(DataCommon):
    """Several datasets as one: ``parts`` {dataset: its data config} (each checked by its own schema)."""
    parts: Dict[str, Any] = field(default_factory=dict)
    leave_out: Any = None           # a part's name or a list (leave-one-dataset-out)
    fold: Optional[int] = None


#: dataset name -> schema (anything else: RecordingsData)
DATA_SCHEMAS = {"simulated": SimulatedData, "rosbag": RosbagData, "general6": GeneralData, "general9": GeneralData}


def data_schema(name: str):
    return DATA_SCHEMAS.get(str(name), RecordingsData)


@dataclass
class GenericDeclarations:
    """Unit/frame declarations of a generic-format recording (tcn_ahrs/datasets/generic.py): HDF5
    root attributes or a CSV's YAML sidecar; also ``declare:`` of conf/data/rosbag.yaml."""
    time_unit: str = "s"               # s | ms | us | ns
    gyr_unit: str = "rad/s"            # rad/s | deg/s
    acc_unit: str = "m/s^2"            # m/s^2 | g
    acc_sign: str = "specific_force"   # specific_force | gravity
    mag_unit: str = "uT"               # uT | G | nT | arbitrary (direction only)
    quat_order: str = "wxyz"           # wxyz | xyzw
    nav_frame: Any = "ENU"             # ENU | NED | NWU | 3x3 C_enu_from_frame (rows)
    gt_body_from_imu: Optional[List[float]] = None  # quaternion (w, x, y, z) or 3x3 matrix; null: identity
    rate: Optional[float] = None       # nominal rate, Hz; null: from t
    clock: str = "stamps"              # stamps | nominal (a regular stream with jittered stamps: the grid)
    mag_hard_iron: Optional[List[float]] = None  # µT (3,), subtracted from the magnetometer; null: none
    gyr_bias: Optional[List[float]] = None       # rad/s (3,), subtracted from the gyro; null: none
    acc_bias: Optional[List[float]] = None       # m/s² (3,), subtracted from the accelerometer; null: none
    mag_soft_iron: Optional[List[List[float]]] = None  # 3x3 (rows), applied after mag_hard_iron; null: identity
    gt_time_offset: float = 0.0        # s the ground truth's stamps run late against the IMU's (read at t + offset)
