"""Every config file composes and instantiates: each primary config with its defaults, every
experiment / model / trainer option with train.yaml, and each script's key check accepts what
its YAML declares (a key added to a YAML but not to the code, or misspelt, fails here)."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tcn_ahrs.config import CONF_DIR

REPO = Path(__file__).resolve().parents[1]
CONF = CONF_DIR  # tcn_ahrs.config: the one place that names the config folder


def _compose(name, overrides=()):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(name, overrides=list(overrides))


def _options(group):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_composes_and_builds_its_model(experiment):
    from tcn_ahrs.model.ahrs import LearnedAHRS
    from tcn_ahrs.config import TrainConfig, check_keys
    from tcn_ahrs.training.run import check_train_values

    cfg = _compose("train", [f"experiment={experiment}"])
    check_keys(cfg.train, TrainConfig, "train")
    check_train_values(cfg.train)
    assert cfg.data.name in _options("data")
    model = LearnedAHRS.from_config(OmegaConf.to_container(cfg.model, resolve=True))
    assert model.axes == int(cfg.data.axes) or (model.axes == 6 and int(cfg.data.axes) == 9)
    # the crossval config is train.yaml + its section: every experiment composes there too
    assert _compose("crossval", [f"experiment={experiment}"]).crossval.folds is None


@pytest.mark.parametrize("trainer", _options("trainer"))
def test_every_trainer_option_composes(trainer, tmp_path):
    cfg = _compose("train", [f"trainer={trainer}"])
    assert {"accelerator", "devices", "precision"} <= set(cfg.trainer)
    if trainer in ("default", "cpu"):  # the others need a GPU / processes to instantiate
        from tcn_ahrs.training.run import build_trainer

        t = build_trainer(cfg, tmp_path, "val/aae_deg")
        assert t.max_epochs == int(cfg.train.epochs)


@pytest.mark.parametrize("data", _options("data"))
def test_every_data_option_composes_with_every_script(data):
    for primary in ("train", "compare", "benchmark", "evaluate"):
        cfg = _compose(primary, [f"data={data}"])
        assert cfg.data.name == data and int(cfg.data.axes) in (6, 9)


def test_script_key_checks_accept_their_own_yaml():
    from tcn_ahrs.experiments.compare import BENCHMARK_KEYS, COMPARE_KEYS
    from tcn_ahrs.evaluate.main import EVAL_KEYS

    top = lambda cfg: set(cfg) - {"data", "hydra"}  # noqa: E731
    assert top(_compose("compare")) <= COMPARE_KEYS
    assert top(_compose("benchmark")) <= BENCHMARK_KEYS
    assert top(_compose("evaluate")) <= EVAL_KEYS
    from tcn_ahrs.config import ExportConfig, keys

    EXPORT_KEYS = keys(ExportConfig)

    assert top(_compose("export")) <= EXPORT_KEYS
    assert _compose("inspect_data").data.name


@pytest.mark.parametrize("paper", _options("paper"))
def test_every_paper_config_composes_and_has_its_experiment(paper):
    from tcn_ahrs.reproduce import papers

    cfg = _compose("reproduce", [f"paper={paper}"])
    assert cfg.paper.name == paper and paper in papers()
