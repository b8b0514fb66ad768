"""The nested family search (tcn_ahrs.experiments.search): the choice rule, and on simulated recordings a
family that cannot win is not chosen, the search resumes from its SQLite studies, and its
numbers are the evaluation runner's."""
from __future__ import annotations

import numpy as np
import pytest

from tcn_ahrs.experiments import search
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.evaluate import evaluate

pytest.importorskip("optuna")

# a device whose gyro reads 3 deg/s off on z and 1 deg/s on x: strapdown integration cannot win
DEVICE = dict(gyro_bias_range_dps=(1.0, 3.0), gyro_bias_repeatability_dps=0.0, gyro_bias_rw_dps=0.0)


def test_choose_prefers_simpler_within_the_tie_margin_and_guards_inclination():
    c = {"backbone (tuned)": (1.00, 0.5), "madgwick (defaults)": (1.01, 0.5), "ecf (tuned)": (0.5, 2.0)}
    # ecf's AAE is best but its inclination is 1.5 deg worse than the bar: not eligible
    assert search.choose(c, tie_margin=0.02, incl_margin=0.05, incl_bar=0.5) == "madgwick (defaults)"
    assert search.choose(c, tie_margin=0.0, incl_margin=0.05, incl_bar=0.5) == "backbone (tuned)"
    assert search.choose(c, tie_margin=0.0, incl_margin=5.0, incl_bar=0.5) == "ecf (tuned)"
    with pytest.raises(ValueError, match="diverged"):
        search.choose({"a": (np.inf, np.inf)}, 0.0, 0.0)


def _record(fold, seed, inner, learned_split=0):
    """A fold x seed record with the fields the choice reads: {name: rows of (AAE, incl.)}."""
    cands = {n: {"family": n.split()[0], "calibration": "learned" if n == "closed_loop" else "none",
                 "tuned": "(tuned)" in n or n == "closed_loop", "inner_val": rows} for n, rows in inner.items()}
    return {"fold": fold, "seed": seed, "candidates": cands, "learned_split": learned_split, "chosen": None}


def test_a_fold_has_one_choice_over_its_seeds():
    """EuRoC fold 0 (measured): the tuned filter's inner score depends on the sampler's seed, so a
    per-seed choice flipped; averaged over the seeds the fold has one choice."""
    seeds = [{"ecf (defaults)": [[3.0, 1.0], [2.0, 1.0]], "backbone (tuned)": [[2.0, 1.0], [1.0, 1.0]]},
             {"ecf (defaults)": [[3.0, 1.0], [2.0, 1.0]], "backbone (tuned)": [[4.0, 1.0], [3.0, 1.0]]},
             {"ecf (defaults)": [[3.0, 1.0], [2.0, 1.0]], "backbone (tuned)": [[2.2, 1.0], [1.2, 1.0]]}]
    recs = [_record(0, k, inner) for k, inner in enumerate(seeds)]
    alone = [search.choose_candidate(r["candidates"], 0, 0.02, 0.05) for r in recs]
    assert alone == ["backbone (tuned)", "ecf (defaults)", "backbone (tuned)"]  # flips with the seed
    assert search.fold_choice(recs, 0.02, 0.05) == "backbone (tuned)"  # mean 2.07 vs 2.5
    # a learned candidate replaces the choice only if better on its own inner split by > tie_margin
    inner = {"ecf (defaults)": [[1.52, 1.0], [3.0, 1.0]], "closed_loop": [[1.5, 1.0]]}
    assert search.fold_choice([_record(0, 0, inner, learned_split=1)], 0.02, 0.05) == "closed_loop"
    assert search.fold_choice([_record(0, 0, inner, learned_split=0)], 0.02, 0.05) == "ecf (defaults)"
    # two learned candidates: the second must beat the first on that split, not the filter
    two = {**inner, "residual": [[1.48, 1.0]]}
    two_rec = _record(0, 0, two, learned_split=1)
    two_rec["candidates"]["residual"]["calibration"] = "learned"
    assert search.fold_choice([two_rec], 0.02, 0.05) == "closed_loop"  # 1.48 is within 2 % of 1.5


def test_release_is_the_most_frequent_fold_choice_ties_read_on_the_inner_validation():
    inner = {"ecf (tuned)": [[2.0, 1.0]], "backbone (defaults)": [[1.0, 1.0]], "closed_loop": [[1.5, 1.0]]}
    folds = [_record(f, 0, inner) for f in range(3)]
    rows = lambda names: [{"fold": f, "seed": 0, "chosen": n} for f, n in enumerate(names)]  # noqa: E731
    res = {"rows": rows(["ecf (tuned)", "ecf (tuned)", "closed_loop"]), "folds": folds}
    assert search.release_choice(res, 0.02)[0] == "ecf (tuned)"  # chosen on 2 of 3 folds
    res["rows"] = rows(["ecf (tuned)", "backbone (defaults)", "closed_loop"])
    assert search.release_choice(res, 0.02)[0] == "backbone (defaults)"  # 1-1-1: the best inner score
    res["folds"] = [_record(f, 0, dict(inner, **{"ecf (tuned)": [[1.01, 1.0]]})) for f in range(3)]
    assert search.release_choice(res, 0.02)[0] == "ecf (tuned)"  # within 2 %: the simpler family


@pytest.fixture(scope="module")
def recs():
    return [simulate(p, 20.0, 100.0, seed=s, device_seed=3, axes=6, **DEVICE)
            for s, p in enumerate(["walking", "slow_rotation", "walking", "fast_rotation"])]


def test_a_family_that_cannot_win_is_not_chosen_and_the_search_resumes(recs, tmp_path):
    train, val, test = recs[:2], recs[2:3], recs[3:]
    storage = f"sqlite:///{tmp_path / 'search.db'}"
    kw = dict(axes=6, families=["strapdown", "madgwick"], calibrations=["none", "gyro_bias"], trials=4, seed=0,
              storage=storage, learned={}, learned_split=0, tie_margin=0.02, incl_margin=0.05, log=lambda _: None)
    rec = search.search_fold(0, [(train, val)], train + val, test, **kw)
    assert rec["chosen"] != "strapdown (defaults)"  # raw integration of the biased gyro
    assert "+cal:gyro_bias" in rec["chosen"]  # the bias is the device's: calibrating it wins
    raw = rec["test"]["strapdown (defaults)"]["aae_deg"]
    assert rec["test"][rec["chosen"]]["aae_deg"] < 0.5 * raw
    # a second run on the same storage continues the studies (no new trials): the same choice
    again = search.search_fold(0, [(train, val)], train + val, test, **kw)
    assert again["chosen"] == rec["chosen"] and again["test"] == rec["test"]
    import optuna

    studies = optuna.get_all_study_summaries(storage)
    assert studies and all(s.n_trials == 4 for s in studies)


def test_calibrated_wrapper_is_what_the_runner_scores(recs):
    from tcn_ahrs import calibration

    cal = calibration.fit_calibration(recs[:2], gyro="bias", acc="none", mag="none")
    est = search.Calibrated(search.FAMILIES["madgwick"].build(6), cal, name="m")
    aae, incl = search.mean_scores(est, recs[3:], 6)
    res = evaluate([est], recs[3:], axes=6)["methods"]["m"]["mean"]
    assert aae == pytest.approx(res["aae_deg"], rel=1e-12) and incl == pytest.approx(res["inclination_deg"], rel=1e-12)


def test_own_device_command_on_generic_recordings(tmp_path, capsys):
    """`tcn-ahrs search data=generic data.root=DIR`: recordings dealt into 3 folds, the report
    written, its chosen column's numbers the runner's."""
    import json

    from tcn_ahrs.cli import main

    root = _generic_root(tmp_path)
    out = tmp_path / "search"
    main(["search", "data=generic", f"data.root={root}", "search.trials=2", "search.seeds=[0]",
          "search.families=[strapdown,madgwick]", "search.calibrations=[none,gyro_bias]", "search.learn=[]",
          f"search.out={out}", f"hydra.run.dir={tmp_path / 'hydra'}"])
    res = json.loads((out / "search.json").read_text())
    assert [r["fold"] for r in res["rows"]] == [0, 1, 2]
    printed = capsys.readouterr().out
    assert "dealt into 3 folds" in printed
    # a lighter search says what it left out, on screen and in the report
    assert "2 Optuna trials per candidate (full: 40)" in printed and "calibrations left out: full" in printed
    assert "Lighter than the full search" in (out / "search.md").read_text()
    for rec, row in zip(res["folds"], res["rows"]):
        assert row["aae_deg"] == rec["test"][rec["chosen"]]["aae_deg"]
    assert (out / "search.md").read_text().startswith("# Family search: generic")
    assert res["release"]["runs"] == 3 and (out / "estimator.json").is_file() == (res["release"]["family"] != "closed_loop")
    # the report's number = a separate `tcn-ahrs evaluate` of that fold's chosen estimator file
    rec = res["folds"][0]
    main(["evaluate", "data=generic", f"data.root={root}", f"data.test={rec['recordings']}", "data.split=test",
                f"ckpt={out / 'fold0_seed0.json'}", f"out={tmp_path / 'ev'}", "plots=false", "trajectories=false",
                f"hydra.run.dir={tmp_path / 'hydra2'}"])
    got = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert got["methods"]["Learned AHRS"]["mean"]["aae_deg"] == pytest.approx(res["rows"][0]["aae_deg"], rel=1e-12)


def _generic_root(tmp_path):
    import h5py

    root = tmp_path / "mine"
    root.mkdir()
    for i, prof in enumerate(["walking", "slow_rotation", "fast_rotation"]):
        s = simulate(prof, 15.0, 100.0, seed=i, device_seed=3)
        with h5py.File(root / f"rec{i}.h5", "w") as f:
            for key, val in (("t", s.time), ("gyr", s.gyro), ("acc", s.accel), ("mag", s.mag), ("quat", s.quat)):
                f[key] = val
    return root


def test_two_job_search_through_the_joblib_launcher(tmp_path):
    """Folds as Hydra multirun jobs (joblib launcher, 2 processes) write their records; a plain
    run combines them without computing anything again and equals a one-process search."""
    import json

    from tcn_ahrs.cli import main

    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    root = _generic_root(tmp_path)
    common = ["data=generic", f"data.root={root}", "search.trials=2", "search.seeds=[0]",
              "search.families=[strapdown,madgwick]", "search.calibrations=[none]", "search.learn=[]"]
    out = tmp_path / "parallel"
    main(["search", "-m", *common, f"search.out={out}", "search.folds=[0],[1]", "hydra/launcher=joblib",
          "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    assert sorted(p.name for p in (out / "records").iterdir()) == ["fold0_seed0.json", "fold1_seed0.json"]
    assert not (out / "search.json").exists()  # jobs write records only: the plain run reports
    seen = {json.loads((out / "records" / f"fold{i}_seed0.json").read_text())["seconds"] for i in (0, 1)}
    main(["search", *common, f"search.out={out}", "search.folds=[0,1]", f"hydra.run.dir={tmp_path / 'h1'}"])
    res = json.loads((out / "search.json").read_text())
    assert {r["seconds"] for r in res["folds"]} == seen  # read, not run again
    ref = tmp_path / "serial"
    main(["search", *common, f"search.out={ref}", "search.folds=[0,1]", f"hydra.run.dir={tmp_path / 'h2'}"])
    serial = json.loads((ref / "search.json").read_text())
    assert [(r["chosen"], r["aae_deg"]) for r in res["rows"]] == [(r["chosen"], r["aae_deg"]) for r in serial["rows"]]
    # a record written with other settings is refused, not silently reused or overwritten
    with pytest.raises(SystemExit):
        main(["search", *common[:-1], "search.calibrations=[none,gyro_bias]", f"search.out={out}",
              "search.folds=[0,1]", f"hydra.run.dir={tmp_path / 'h3'}"])


def test_released_estimator_file_runs_in_evaluate_and_export_refuses_it(tmp_path, recs):
    import json

    from tcn_ahrs import calibration
    from tcn_ahrs.estimators.families import load_estimator, save_estimator

    cal = calibration.fit_calibration(recs[:2], gyro="bias", acc="none", mag="none")
    path = tmp_path / "estimator.json"
    save_estimator(path, "madgwick", 6, {"beta": 0.02}, cal, {"dataset": "simulated"})
    est = load_estimator(path, name="chosen")
    ref = search.Calibrated(search.FAMILIES["madgwick"].build(6, beta=0.02), cal, name="ref")
    res = evaluate([est, ref], recs[3:], axes=6)["methods"]
    assert res["chosen"]["mean"]["aae_deg"] == res["ref"]["mean"]["aae_deg"]
    doc = json.loads(path.read_text())
    doc["family"] = "kalman"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="field 'family'"):
        load_estimator(tmp_path / "bad.json")
    from omegaconf import OmegaConf

    from tcn_ahrs.export import export_main
    cfg = OmegaConf.create({"ckpt": str(path), "out": str(tmp_path / "m.pt"), "format": "torchscript", "mode": "both",
                            "rate": None, "overwrite": False})
    with pytest.raises(ValueError, match="classical estimator chosen by tcn-ahrs search"):
        export_main(cfg)


def test_a_learned_gain_must_stand_above_its_spread():
    """search.learn: a learned candidate replaces the classical choice only when its mean gain over
    the validation recordings exceeds the tie margin plus one standard error of the paired gains."""
    from tcn_ahrs.experiments.search.learn import gain_supported

    assert gain_supported([2.0, 2.0, 2.0], [1.5, 1.6, 1.4], 0.02)[0]  # 0.5 deg better on each
    # better on the mean (1.33 vs 2.0) only through one recording: the spread does not support it
    ok, why = gain_supported([2.0, 2.0, 2.0], [0.1, 2.1, 2.0], 0.02)
    assert not ok and "standard error" in why
    assert not gain_supported([2.0, 2.0, 2.0], [1.99, 1.98, 1.99], 0.02)[0]  # inside the 2 % tie margin
    assert not gain_supported([2.0], [0.5], 0.02)[0]  # one recording: no spread, no adoption
    ok, why = gain_supported([2.0, 2.0], [1.0, 1.1], 0.02)  # two: the search cannot decide
    assert not ok and "cannot decide" in why
    assert not gain_supported([2.0, 2.0, 2.0], [1.0, 1.0, float("inf")], 0.02)[0]
    with pytest.raises(ValueError):
        gain_supported([2.0, 2.0], [1.0], 0.02)


def test_the_fold_choice_reads_the_learned_gain_recording_by_recording():
    def rec(learned_recs):
        inner = {"ecf (defaults)": [[2.0, 1.0]], "closed_loop": [[float(np.mean(learned_recs)), 1.0]]}
        r = _record(0, 0, inner)
        r["candidates"]["ecf (defaults)"]["inner_val_recordings"] = [[2.0, 2.0, 2.0]]
        r["candidates"]["closed_loop"]["inner_val_recordings"] = [learned_recs]
        return r

    assert search.fold_choice([rec([1.5, 1.6, 1.4])], 0.02, 0.05) == "closed_loop"
    assert search.fold_choice([rec([0.1, 2.1, 2.0])], 0.02, 0.05) == "ecf (defaults)"
    # over seeds the per-recording scores are averaged first (here: 1.45, 1.8, 1.65 -> supported)
    assert search.fold_choice([rec([1.4, 1.6, 1.4]), rec([1.5, 2.0, 1.9])], 0.02, 0.05) == "closed_loop"


def test_the_budget_is_shared_among_the_trainings():
    from tcn_ahrs.experiments.search.learn import share_minutes
    from tcn_ahrs.experiments.search.progress import CLASSICAL_SHARE, Budget

    assert share_minutes(None, 0.0, 3) is None
    assert share_minutes(10.0, 2.0, 4, 2.0) == pytest.approx(1.5)
    assert share_minutes(10.0, 12.0, 2) == 0.5  # over budget: the floor (and the overrun is said)
    b = Budget(12.0, n_trainings=4, n_folds=3)
    with b.training() as first:
        assert first == pytest.approx((12.0 - CLASSICAL_SHARE * 12.0) / 4, rel=1e-3)
    assert b.trainings_left == 3
    b.fold_done()
    assert b.folds_left == 2 and len(b.classical_per_fold) == 1
    assert Budget(None, 2, 2).overrun() is None
    assert "budget 12 min" in b.describe(1) and "none" in Budget(5.0, 0, 3).describe(0)


def test_the_expected_gain_over_the_best_classical_filter():
    from tcn_ahrs.experiments.search.report import expected_gain

    rows = [{"aae_deg": a, "best_classical_aae_deg": 2.0} for a in (1.0, 1.5, 2.5)]
    g = expected_gain(rows)
    assert g["mean"] == pytest.approx(np.mean([0.5, 0.25, -0.25])) and g["n"] == 3
    assert "17% better" in g["sentence"] and "worst -25%" in g["sentence"]
    assert "worse" in expected_gain([{"aae_deg": 3.0, "best_classical_aae_deg": 2.0}])["sentence"]


def test_the_search_trains_a_learned_candidate_in_its_folds_and_resumes(tmp_path, capsys):
    """`tcn-ahrs search ... search.learn=[finetune]`: the recipe trained in every outer fold on the
    inner training recordings (never the outer fold's), compared recording by recording on the inner
    validation ones, scored on the outer fold beside the classical candidates; one progress bar and a
    summary with the expected gain; a second run reuses every training."""
    import json

    from tcn_ahrs.cli import main

    root = _generic_root(tmp_path)
    out = tmp_path / "search"
    args = ["search", "data=generic", f"data.root={root}", "search.trials=2", "search.seeds=[0]",
            "search.families=[strapdown,madgwick]", "search.calibrations=[none]", "search.learn=[finetune]",
            "search.budget_minutes=6", f"search.out={out}", f"hydra.run.dir={tmp_path / 'hydra'}"]
    main(args)
    printed = capsys.readouterr().out
    res = json.loads((out / "search.json").read_text())
    name = "residual (fine-tuned general)"
    for rec in res["folds"]:
        c = rec["candidates"][name]
        assert c["calibration"] == "learned" and len(c["inner_val_recordings"][0]) >= 1
        assert rec["test"][name]["aae_deg"] > 0  # scored on the outer fold like every candidate
        # cross-fitted: epoch and knobs chosen on each half of the validation recordings (one half for one)
        runs = sorted((out / "learn" / f"fold{rec['fold']}" / "finetune").glob("chosen_on_half*"))
        assert len(runs) == min(2, len(c["inner_val_recordings"][0]))
        for run in runs:
            cfg = (run / "config_resolved.yaml").read_text()
            assert (run / "TRAINED").is_file()
            assert "max_time: 00:00:" in cfg  # the budget's cap
        line = next(x for x in printed.splitlines() if f"fold {rec['fold']}: training {name} on" in x)
        trained_on = line.split(" on ", 1)[1].split(", epoch and knobs chosen on")[0]
        assert not any(r in trained_on for r in rec["recordings"])  # the outer fold's recordings train nothing
    assert "trained in each of 3 outer folds" in printed and "budget 6 min" in printed
    assert "[search 100%" in printed  # the bar (a line per 10 % where stderr is no terminal)
    assert "== search summary" in printed and "expected on new recordings of this device:" in printed
    assert res["expected_gain"]["n"] == 3
    stamps = {p: p.stat().st_mtime for p in out.glob("learn/fold*/finetune/*/TRAINED")}
    assert len(stamps) >= 3
    main(args)  # resumed: records and trainings read, nothing trained again
    again = json.loads((out / "search.json").read_text())
    assert {p: p.stat().st_mtime for p in out.glob("learn/fold*/finetune/*/TRAINED")} == stamps
    assert [r["aae_deg"] for r in again["rows"]] == [r["aae_deg"] for r in res["rows"]]


def test_a_learned_release_is_a_checkpoint_with_its_card_that_evaluate_runs(tmp_path):
    """A learned candidate chosen on most folds: its recipe trained on every recording but the last
    fold's (which chooses its knobs), written atomically as release.ckpt with release.md; `tcn-ahrs
    evaluate ckpt=release.ckpt` runs it and it exports."""
    import json

    from omegaconf import OmegaConf

    from tcn_ahrs.cli import main
    from tcn_ahrs.experiments.search import release_learned

    root = _generic_root(tmp_path)
    cfg = OmegaConf.create({"data": {"name": "generic", "root": str(root), "axes": 9}})
    name = "residual (fine-tuned general)"
    rows = [{"fold": f, "seed": 0, "chosen": name, "aae_deg": 1.0, "best_classical_aae_deg": 1.2} for f in range(3)]
    from tcn_ahrs.datasets import load_split

    every = [s for s in load_split({"name": "generic", "root": str(root), "split": "all", "axes": 9}, "all")]
    folds = [["rec0"], ["rec1"], ["rec2"]]
    info = release_learned(cfg, {"rows": rows}, tmp_path / "out", name, {"checkpoint": None}, every, folds, 9, None)
    assert info["trained_on"] == ["rec0", "rec1"] and info["validated_on"] == ["rec2"]
    card = (tmp_path / "out" / "release.md").read_text()
    assert "17% better than the best classical filter" in card and "3 of 3 outer fold" in card
    assert not list((tmp_path / "out").glob("*.partial"))
    main(["evaluate", "data=generic", f"data.root={root}", "data.split=all", f"ckpt={info['path']}",
          f"out={tmp_path / 'ev'}", "plots=false", "trajectories=false", f"hydra.run.dir={tmp_path / 'h'}"])
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["methods"]["Learned AHRS"]["mean"]["aae_deg"] > 0
    main(["export", f"ckpt={info['path']}", f"out={tmp_path / 'm.onnx'}", "format=onnx", "mode=streaming"])
    assert list(tmp_path.glob("m*.onnx"))


def test_the_device_check_is_a_calibration_the_classical_candidates_run_on(tmp_path):
    """search.calibrations=[..., device_check]: a classical candidate on each recording's own gyro bias
    at rest; its estimator file holds {"kind": "device_check"} and runs what `tcn-ahrs evaluate`
    runs without a checkpoint (the backbone with VQF's defaults on device-checked recordings)."""
    from tcn_ahrs.device_check import RestBiasCalibration, checked
    from tcn_ahrs.estimators.families import fit_named_calibration, load_estimator, save_estimator
    from tcn_ahrs.evaluate.main import default

    seq = simulate("walking", 40.0, 100.0, seed=3, device_seed=4, axes=6, gyro_bias_range_dps=(4.9, 5.0))
    cal = fit_named_calibration("device_check", [])
    assert isinstance(cal, RestBiasCalibration)
    fam = search.FAMILIES["backbone"]
    save_estimator(tmp_path / "e.json", "backbone", 6, fam.defaults_for(6), cal, {})
    est = load_estimator(tmp_path / "e.json", name="file")
    raw = search.Calibrated(fam.build(6, **fam.defaults_for(6)), None, name="raw")
    res = evaluate([est, raw], [seq], axes=6)["methods"]
    ref = evaluate([default(6)], checked([seq]), axes=6)["methods"]["Backbone (default)"]["mean"]["aae_deg"]
    assert res["file"]["mean"]["aae_deg"] == pytest.approx(ref, rel=1e-12)
    assert res["file"]["mean"]["aae_deg"] < 0.2 * res["raw"]["mean"]["aae_deg"]  # 5 deg/s is beyond VQF's clip
    with pytest.raises(ValueError, match="unknown 'nope'"):
        fit_named_calibration("nope", [])


def test_a_learned_checkpoint_with_its_networks_off_is_called_the_backbone(tmp_path):
    import torch

    from tcn_ahrs.checkpoint import load_checkpoint
    from tcn_ahrs.checkpoint import networks_off
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    assert networks_off(repo / "checkpoints" / "broad9_residual.ckpt")  # trust_weight 0, gyro_clip 0
    ck = load_checkpoint(repo / "checkpoints" / "broad9_residual.ckpt")
    ck["tcn_ahrs"]["model"]["residual"]["trust_weight"] = 0.5
    torch.save(ck, tmp_path / "on.ckpt")
    assert not networks_off(tmp_path / "on.ckpt") and not networks_off(None)


def _device_root(tmp_path, n=6, seconds=30.0, profile="walking", **device):
    root = tmp_path / "device"
    root.mkdir()
    for i in range(n):
        s = simulate(profile, seconds, 100.0, seed=10 + i, device_seed=5, axes=6, **device)
        np.savetxt(root / f"rec{i}.csv", np.column_stack([s.time, s.gyro, s.accel, s.quat]), delimiter=",",
                   comments="", fmt="%.10g", header="t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,quat_w,quat_x,quat_y,quat_z")
    return root


def test_a_learned_candidate_that_cannot_win_is_not_chosen(tmp_path):
    """A device with a 5 deg/s gyro bias (3 deg/s more or less per recording) that rests now and then:
    each recording's own bias read at rest (the device check) is what wins, and the classical
    filters have it too (search.calibrations device_check), so the fine-tuned general model — whose
    edge over the raw filters was that same check — is scored but never chosen. (Measured: outer
    AAE 0.54-0.64 deg for integration on checked input vs 0.83-0.96 for the learned candidate.)"""
    import json

    from tcn_ahrs.cli import main

    root = _device_root(tmp_path, gyro_bias_range_dps=(5.0, 5.1), gyro_bias_repeatability_dps=3.0,
                        gyro_bias_rw_dps=0.0)
    out = tmp_path / "search"
    main(["search", "data=generic", f"data.root={root}", "data.axes=6", "search.trials=2", "search.seeds=[0]",
          "search.families=[strapdown,madgwick]", "search.calibrations=[none,device_check]",
          "search.learn=[finetune]", "search.budget_minutes=5", f"search.out={out}", f"hydra.run.dir={tmp_path / 'h'}"])
    res = json.loads((out / "search.json").read_text())
    name = "residual (fine-tuned general)"
    for rec in res["folds"]:
        assert rec["chosen"] != name and rec["test"][name]["aae_deg"] > 0
        assert rec["test"][name]["aae_deg"] < 0.2 * rec["test"]["madgwick (defaults)"]["aae_deg"]  # it learned the bias
    assert res["release"]["chosen"] != name and (out / "estimator.json").is_file()
    assert not (out / "release.ckpt").exists()


def test_a_learned_candidate_that_must_win_is_chosen_and_released(tmp_path):
    """A drone (sustained accelerations) whose gyro reads 5 deg/s off, searched against raw strapdown
    integration alone: integration drifts by degrees a second, the fine-tuned general model (the
    backbone's bias estimation, the device check) holds the attitude, so the rule must adopt it on
    every fold — by a gain far above its spread — and release it as release.ckpt with its card. Nine
    recordings: each inner validation holds three (with two the search cannot decide, and says so)."""
    import json

    from tcn_ahrs.cli import main

    root = _device_root(tmp_path, n=9, profile="drone", gyro_bias_range_dps=(5.0, 5.1),
                        gyro_bias_repeatability_dps=0.5, gyro_bias_rw_dps=0.0)
    out = tmp_path / "search"
    main(["search", "data=generic", f"data.root={root}", "data.axes=6", "search.trials=2", "search.seeds=[0]",
          "search.families=[strapdown]", "search.calibrations=[none]", "search.learn=[finetune]",
          "search.budget_minutes=5", f"search.out={out}", f"hydra.run.dir={tmp_path / 'h'}"])
    res = json.loads((out / "search.json").read_text())
    name = "residual (fine-tuned general)"
    assert [r["chosen"] for r in res["rows"]] == [name] * 3
    for rec in res["folds"]:
        assert rec["test"][name]["aae_deg"] < 0.5 * rec["test"]["strapdown (defaults)"]["aae_deg"]
    assert res["release"]["chosen"] == name and (out / "release.ckpt").is_file() and (out / "release.md").is_file()
    assert res["expected_gain"]["mean"] > 0.5


def test_adoption_passes_on_noise_at_most_at_its_stated_level():
    """A learned candidate no better than the classical choice (its per-recording AAE the choice's
    plus zero-mean noise) is adopted in at most 5 % of draws, for 3 to 12 validation recordings
    (one standard error, the rule before, let it through in about 25 % of draws with 2 recordings and
    16 % with 3); a real 20 % gain is adopted."""
    from tcn_ahrs.experiments.search.learn import ADOPTION_LEVEL, gain_supported

    rng = np.random.default_rng(0)
    for n in (3, 5, 12):
        adopted = 0
        for _ in range(2000):
            ref = rng.uniform(1.0, 4.0, n)
            adopted += gain_supported(ref, ref + rng.normal(0.0, 0.3, n), 0.0)[0]
        assert adopted / 2000 <= ADOPTION_LEVEL + 0.015, (n, adopted)
    ref = rng.uniform(1.0, 4.0, 8)
    assert gain_supported(ref, 0.8 * ref + rng.normal(0.0, 0.05, 8), 0.02)[0]
    # what the test said is printed per learned candidate (a "cannot decide" is never silent)
    from tcn_ahrs.experiments.search.choice import adoption_reasons

    cands = {"ecf (defaults)": {"calibration": "none", "tuned": False, "inner_val": [[2.0, 1.0]],
                                "inner_val_recordings": [[2.0, 2.1]]},
             "residual (trained)": {"calibration": "learned", "tuned": True, "inner_val": [[1.0, 1.0]],
                                    "inner_val_recordings": [[1.0, 1.1]]}}
    why = adoption_reasons(cands, 0, 0.02, 0.5)["residual (trained)"]
    assert why.startswith("against ecf (defaults)") and "cannot decide" in why


def test_no_learned_candidate_starts_from_weights_that_saw_the_outer_fold(tmp_path, monkeypatch):
    """The fine-tuned and residual recipes started from general{axes}_residual.ckpt, which trained and
    chose its knobs on every training recording of BROAD, EuRoC, TUM VI and OxIOD — the outer fold's
    included: on a dataset in the mix they are left out, said, and never trained; your own recordings
    (data=generic) and the closed loop (trained from scratch) are not."""
    from tcn_ahrs.experiments.search import learn
    from tcn_ahrs.experiments.search.progress import Budget
    from tcn_ahrs.training import run as training_run

    def no_training(*a, **k):
        raise AssertionError("trained from leaking weights")

    monkeypatch.setattr(training_run, "train_main", no_training)
    said = []
    got = learn.train_fold_candidates(["finetune", "residual"], tmp_path, 0, [], [],
                                      ["data=euroc", "data.axes=6", "data.fold=null"], 6, Budget(None, 2, 1),
                                      log=said.append)
    assert got == {}
    assert sum("left out: its starting model general6_residual.ckpt trained on euroc's" in s for s in said) == 2, said
    for dataset, axes in (("broad", 9), ("oxiod", 9), ("tumvi", 6)):
        assert learn.starting_leak("finetune", axes, dataset)
    assert learn.starting_leak("finetune", 9, "generic") is None and learn.starting_leak("closed_loop", 6, "euroc") is None


def test_a_leaking_recipe_starts_from_the_general_model_trained_without_the_data(tmp_path, monkeypatch):
    """Where the shipped starting model saw the search's dataset, the recipe starts from the general
    model trained without it (``tcn-ahrs benchmark lodo``'s run, ``search.lodo_runs``): its resolved
    config must leave that dataset out; one that left out another dataset is not taken."""
    from tcn_ahrs.experiments.search import learn
    from tcn_ahrs.training import run as training_run

    seen = []

    def fake_train(cfg, train_seqs=None, val_seqs=None, overrides=()):
        seen.append(list(overrides))
        ck = tmp_path / "trained.ckpt"
        ck.write_text("")
        return {"best": str(ck)}

    monkeypatch.setattr(training_run, "train_main", fake_train)
    for left in ("broad", "euroc"):
        run = tmp_path / "lodo" / "euroc"
        (run / "checkpoints").mkdir(parents=True, exist_ok=True)
        (run / "checkpoints" / "last.ckpt").write_text("")
        (run / "knobs.json").write_text("{}")
        (run / "config_resolved.yaml").write_text(f"data:\n  leave_out: {left}\n")
        args = ["data=euroc", "data.axes=6", "data.fold=null"]
        (tmp_path / f"r_{left}").mkdir()
        if left != "euroc":
            with pytest.raises(ValueError, match="none found in"):
                learn.train_recipe("finetune", tmp_path / f"r_{left}", [], [], args, 6, 1.0,
                                   lodo_runs={"6": str(tmp_path / "lodo")})
            assert not seen
        else:
            learn.train_recipe("finetune", tmp_path / f"r_{left}", [], [], args, 6, 1.0,
                               lodo_runs={"6": str(tmp_path / "lodo")})
            assert f"init={run / 'checkpoints' / 'last.ckpt'}" in seen[0]
            assert not any("general6_residual" in a for a in seen[0])


def test_the_adoption_reads_recordings_that_chose_nothing(tmp_path, monkeypatch):
    """A learned candidate's epoch and inference knobs are chosen on validation recordings; its
    adoption test read its scores on those same recordings (optimistic: crossval's own comment
    measured 1.77 against 3.15). Cross-fitted now: each validation recording is run by a model whose
    epoch and knobs were chosen on the other recordings only, both trained on the same training ones."""
    from types import SimpleNamespace

    from tcn_ahrs.experiments.search import learn
    from tcn_ahrs.experiments.search.progress import Budget

    trained = []

    def fake_train(recipe, run_dir, train, val, data_args, axes, minutes, seed=0, **kw):
        trained.append(([s.name for s in train], [s.name for s in val]))
        return [s.name for s in val]          # the "checkpoint": what chose its epoch and knobs

    class Stub:
        def __init__(self, chose, name):
            self.chose, self.name, self.ckpt_path = chose, name, None

        def run(self, seq, init_quat=None, init_index=0):
            return self.chose

    monkeypatch.setattr(learn, "train_recipe", fake_train)
    monkeypatch.setattr(learn, "learned_estimator", lambda path, name: Stub(path, name))
    train = [SimpleNamespace(name=f"t{i}") for i in range(4)]
    val = [SimpleNamespace(name=f"v{i}") for i in range(5)]
    got = learn.train_fold_candidates(["closed_loop"], tmp_path, 0, train, val, ["data=generic"], 6, Budget(None, 2, 1),
                                      log=lambda s: None)
    cand = got[learn.candidate_name("closed_loop")]
    for s in val:
        assert s.name not in cand.run(s), (s.name, cand.run(s))   # never scored by what it tuned
    assert all(tr == [s.name for s in train] for tr, _ in trained)  # every model on the same training recordings
    assert sorted(sum((v for _, v in trained), [])) == sorted(s.name for s in val)


def test_a_candidates_real_error_is_raised_not_scored_as_diverged():
    """Only numerical failure counts as divergence: a ValueError inside a candidate (a refusal, a bug)
    was scored as "diverged" (an infinite score) and the candidate silently dropped."""
    from tcn_ahrs.estimators.families import recording_scores

    class Numerical:
        name = "numerical"

        def run(self, seq, q0=None, k0=0):
            raise ZeroDivisionError("a knob point the kernel cannot run")

    class Refusing:
        name = "refusing"

        def run(self, seq, q0=None, k0=0):
            raise ValueError("field 'mag': needs a magnetometer")

    seqs = [simulate("walking", 5.0, 100.0, seed=1, axes=6)]
    assert recording_scores(Numerical(), seqs, 6)[0] == [float("inf")]
    with pytest.raises(ValueError, match=r"refusing on .*needs a magnetometer"):
        recording_scores(Refusing(), seqs, 6)
