"""The command line (``tcn-ahrs COMMAND``, tcn_ahrs/cli.py) and the installed wheel: configs ship in
the package, so ``tcn-ahrs evaluate`` runs from outside the repository."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tcn_ahrs import cli
from tcn_ahrs.conf import CONF_DIR

REPO = Path(__file__).resolve().parents[1]


def test_every_command_has_its_main_config_and_target():
    import importlib

    for name, command in cli.COMMANDS.items():
        assert (CONF_DIR / f"{command.config}.yaml").is_file(), name
        module, func = command.target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), command.target
    for mode, target in cli.BENCHMARK_MODES.items():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), mode


def test_scripts_are_thin_wrappers_of_the_commands():
    """Each scripts/<command>.py runs ``tcn_ahrs.cli.main`` with its command: one code path."""
    for command in cli.COMMANDS.values():
        text = (REPO / "scripts" / f"{command.config}.py").read_text()
        assert "from tcn_ahrs.cli import main" in text and "hydra.main" not in text


@pytest.mark.parametrize("argv, message", [
    (["trian"], "unknown command 'trian' (did you mean 'train'?)"),
    (["benchmark", "sped"], "benchmark: unknown mode 'sped'"),
    (["train", "train.epoch=3"], "did you mean 'train.epochs'?"),
    (["evaluate", "data=nope"], "Could not find 'data/nope'"),
])
def test_user_errors_are_one_line_with_exit_2(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_no_command_prints_the_commands(capsys):
    cli.main([])
    out = capsys.readouterr().out
    assert all(name in out for name in cli.COMMANDS)


@pytest.mark.slow
def test_wheel_runs_evaluate_outside_the_repository(tmp_path):
    """Build the wheel from the sources, install it into an empty folder (no editable install, no
    checkout on the path) and run ``tcn-ahrs evaluate`` there on the built-in simulator: the
    configs and the shipped models (run by name) must come from inside the wheel."""
    src = tmp_path / "src"
    src.mkdir()
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "pyproject.toml", "setup.py", "README.md", "tcn_ahrs", "conf",
                            "checkpoints"],
                           cwd=REPO, capture_output=True, text=True, check=True).stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    for f in files:
        if (REPO / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            (src / f).write_bytes((REPO / f).read_bytes())
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                    "-q", "-w", str(dist), str(src)], check=True, capture_output=True)
    wheel = next(dist.glob("tcn_ahrs-*.whl"))
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target", str(site),
                    str(wheel)], check=True, capture_output=True)
    assert (site / "tcn_ahrs" / "conf" / "data" / "simulated.yaml").is_file()
    assert (site / "tcn_ahrs" / "export" / "c" / "model.c.in").is_file()  # format=c's templates
    shipped = site / "tcn_ahrs" / "checkpoints"
    assert {"general6_residual.ckpt", "general9_residual.ckpt", "tumvi6_ecf.json"} <= {p.name for p in shipped.iterdir()}
    assert not (shipped / "closed_loop").exists()  # the other families' files stay in the checkout

    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    where = subprocess.run([sys.executable, "-c", "import tcn_ahrs; print(tcn_ahrs.__file__)"], cwd=work, env=env,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert where.startswith(str(site)), where  # the wheel's copy, not the checkout
    out = work / "eval"
    run = subprocess.run([str(site / "bin" / "tcn-ahrs"), "evaluate", "ckpt=broad9_residual",   # by name, from the wheel
                          "data=simulated", "data.split=test", f"out={out}", "plots=false", "trajectories=false"],
                         cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert f"the shipped {shipped / 'broad9_residual.ckpt'}" in run.stdout
    results = json.loads((out / "results.json").read_text())
    assert results, "evaluate wrote no results"
    # the default (no ckpt=) needs no file of the checkout: the backbone with VQF's defaults
    run = subprocess.run([str(site / "bin" / "tcn-ahrs"), "evaluate", "data=simulated", "data.split=test",
                          f"out={work / 'default'}", "plots=false", "trajectories=false"],
                         cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "Backbone (default)" in json.loads((work / "default" / "results.json").read_text())["methods"]


def test_a_rerun_child_takes_its_command_from_the_environment(monkeypatch, capsys):
    """Lightning's DDP launcher re-runs ``sys.argv`` (program + overrides, no command word): the
    command comes from ``TCN_AHRS_COMMAND``, which the parent set."""
    monkeypatch.setenv(cli.COMMAND_ENV, "evaluate")
    with pytest.raises(SystemExit) as e:
        cli.main(["data=nope"])
    assert e.value.code == 2 and "evaluate config" in capsys.readouterr().err


def test_old_experiment_names_run_their_new_config(capsys):
    """The renames (README, "Renamed"): every old experiment name maps to a config that exists and
    the old file is gone; the command line runs the new one and says so."""
    from tcn_ahrs.app import check_overrides
    from tcn_ahrs.conf import CONF_DIR
    from tcn_ahrs.config.renamed import EXPERIMENTS, experiment_overrides

    for old, new in EXPERIMENTS.items():
        assert (CONF_DIR / "experiment" / f"{new}.yaml").is_file(), new
        assert not (CONF_DIR / "experiment" / f"{old}.yaml").exists(), old
    args, notes = experiment_overrides(["experiment=broad9_res", "data.fold=0", "+experiment=euroc6"])
    assert args == ["experiment=broad9_residual", "data.fold=0", "+experiment=euroc6_open_loop"]
    assert notes == ['note: experiment=broad9_res is now experiment=broad9_residual (README, "Renamed")',
                     'note: experiment=euroc6 is now experiment=euroc6_open_loop (README, "Renamed")']
    check_overrides("train", ["experiment=euroc6_residual_small"])   # its defaults name the renamed residual
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "experiment=broad9_res", "data=nope"])
    assert e.value.code == 2
    assert "is now experiment=broad9_residual" in capsys.readouterr().out


def test_shipped_models_by_new_and_old_name(capsys):
    from tcn_ahrs.checkpoints import SHIPPED_DIR
    from tcn_ahrs.config.renamed import CHECKPOINTS
    from tcn_ahrs.evaluate.main import shipped

    for old, new in CHECKPOINTS.items():
        assert shipped(new) in (str(SHIPPED_DIR / f"{new}.ckpt"), str(SHIPPED_DIR / f"{new}.json"))
        assert shipped(old) == shipped(new)
        assert not (SHIPPED_DIR / f"{old}.ckpt").exists() and not (SHIPPED_DIR / f"{old}.json").exists()
    assert shipped("checkpoints/broad9.ckpt") == str(SHIPPED_DIR / "broad9_residual.ckpt")
    out = capsys.readouterr().out
    assert 'ckpt=general9 is now ckpt=general9_residual (README, "Renamed")' in out
    with pytest.raises(FileNotFoundError, match="shipped: broad6_residual"):
        shipped("nope")


def test_every_shipped_file_a_config_names_exists():
    """A config naming ``checkpoints/<file>`` (experiment=finetune's ``init``) names a shipped file
    (the renames left ``general${data.axes}.ckpt`` pointing nowhere), and from a wheel it resolves."""
    import re

    from tcn_ahrs.checkpoints import SHIPPED_DIR
    from tcn_ahrs.conf import CONF_DIR
    from tcn_ahrs.evaluate.main import shipped

    named = set()
    for f in CONF_DIR.rglob("*.yaml"):
        for m in re.findall(r"checkpoints/[\w${}.]+\.(?:ckpt|json)", f.read_text()):
            named |= {m.replace("${data.axes}", a) for a in ("6", "9")}
    assert "checkpoints/general9_residual.ckpt" in named
    for path in sorted(named):
        assert (REPO / path).is_file(), path
        assert shipped(str(Path("/nonexistent") / path)) == str(SHIPPED_DIR / Path(path).name), path


def test_train_takes_out_as_its_run_dir_and_says_so(capsys):
    """`tcn-ahrs train out=DIR`, as evaluate and search take it: train's folder is run_dir= (Hydra
    said "Could not override 'out'")."""
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "out=/tmp/my_training", "data=nope"])   # stops at the bad data option, after the alias
    assert e.value.code == 2
    captured = capsys.readouterr()
    assert "out= is run_dir=" in captured.out and "Could not override 'out'" not in captured.err
    assert cli.hydra_arguments("train", ["out=/tmp/x"])[0] == ["run_dir=/tmp/x"]
    assert cli.hydra_arguments("evaluate", ["out=/tmp/x"])[0] == ["out=/tmp/x"]


def test_a_path_with_spaces_and_non_ascii_letters_works(capsys):
    """Hydra's grammar refuses non-ASCII letters and apostrophes unquoted (LexerNoViableAltException);
    the value is quoted for it and said; spaces alone parse as they are."""
    path = "/tmp/Müller's runs/é"
    cli.main(["evaluate", f"out={path}", "--cfg", "job"])   # prints the composed config
    captured = capsys.readouterr().out
    assert f"\nout: {path}\n" in captured and "quoted for Hydra" in captured, captured[-600:]
    args, notes = cli.hydra_arguments("evaluate", ["out=/tmp/my runs", "baselines=[vqf, ecf]"])
    assert args == ["out=/tmp/my runs", "baselines=[vqf, ecf]"] and not notes


def test_a_read_only_working_folder_puts_hydras_run_folder_in_the_temporary_folder(tmp_path, monkeypatch, capsys):
    """A working folder this process cannot write: Hydra's run folder (./runs/...) would stop the
    command with PermissionError('runs'); it goes to the temporary folder, said, and the command runs."""
    from tcn_ahrs import app

    work = tmp_path / "read_only"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.setattr(app, "writable", lambda folder: Path(folder).resolve() != work.resolve())
    monkeypatch.setattr(sys, "argv", ["tcn-ahrs"])
    cli.main(["inspect", "data=simulated", "data.split=test"])
    out = capsys.readouterr().out
    assert "is not writable: Hydra's run folder" in out
    assert not (work / "runs").exists() and list(work.iterdir()) == []


def test_an_existing_read_only_out_is_refused_not_replaced(tmp_path, monkeypatch):
    """An empty out= folder the process cannot write was swapped for a new writable one without a
    word: it is refused, named."""
    from tcn_ahrs import app

    out = tmp_path / "results"
    out.mkdir()
    monkeypatch.setattr(app, "writable", lambda folder: Path(folder) != out)
    with pytest.raises(ValueError, match=r"out=.*results is not writable"):
        with app.staged_output(out):
            pass
    assert out.is_dir() and list(out.iterdir()) == []
