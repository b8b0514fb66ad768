"""Monte Carlo localisation with KLD-sampling (tcn_ahrs.nav.particle, issue 14)."""
import math

import numpy as np
import pytest
import torch

from tcn_ahrs.nav.arena import Arena, Scanner, drive_rectangle
from tcn_ahrs.nav.particle import (LikelihoodField, Mcl, MclParams, kld_bound, low_variance_resample,
                                   multinomial_resample)


@pytest.mark.parametrize("resample", [low_variance_resample, multinomial_resample])
def test_resampling_is_unbiased_and_takes_unnormalised_weights(resample):
    from scipy.stats import chisquare

    g = torch.Generator().manual_seed(0)
    w = torch.rand(40, generator=g, dtype=torch.float64) ** 2
    reps, n = 3000, 40
    counts = torch.zeros(40, dtype=torch.float64)
    for _ in range(reps):
        counts += torch.bincount(resample(w, n, g), minlength=40)
    expected = (w / w.sum() * n * reps).numpy()
    assert chisquare(counts.numpy(), expected).pvalue > 1e-3
    # the same draws for weights scaled by any positive factor (no normalisation needed)
    a = resample(w * 1e-30, n, torch.Generator().manual_seed(5))
    b = resample(w * 1e6, n, torch.Generator().manual_seed(5))
    assert torch.equal(a, b)


def test_kld_bound_matches_the_chi_square_closed_form():
    from scipy.stats import chi2

    eps, delta = 0.05, 0.01
    k = torch.arange(2, 2001)
    exact = chi2.ppf(1 - delta, k.numpy() - 1) / (2 * eps)
    approx = kld_bound(k, eps, delta).numpy()
    rel = np.abs(approx - exact) / exact
    assert rel[k.numpy() >= 10].max() < 0.005 and rel.max() < 0.1   # Wilson-Hilferty: exact as k grows
    assert kld_bound(torch.tensor([1]), eps, delta).item() == 1.0


def test_likelihood_field_is_the_brute_force_nearest_obstacle_distance():
    rng = np.random.default_rng(2)
    grid = rng.random((12, 15)) < 0.15
    res = 0.05
    field = LikelihoodField(grid, res, (0.0, 0.0), MclParams())
    occ = np.argwhere(grid)
    cells = np.argwhere(np.ones_like(grid))
    brute = np.sqrt(((cells[:, None, :] - occ[None]) ** 2).sum(-1)).min(1).reshape(grid.shape) * res
    np.testing.assert_allclose(field.distance_np, brute, atol=1e-12)
    # and the beam model's look-up reads it at the cell of a point
    x, y = torch.tensor([0.26]), torch.tensor([0.41])
    assert float(field.lookup(x, y)) == pytest.approx(brute[8, 5], abs=1e-6)


def _arena_run(params, kidnap=None, laps=2, seed=0):
    arena, sc = Arena(), Scanner()
    grid, res, origin = arena.grid()
    mcl = Mcl(LikelihoodField(grid, res, origin, params), params, kld=True, seed=seed + 1)
    angles = torch.as_tensor(sc.angles(), dtype=torch.float32)

    def est(prev, now, r):
        return mcl.step(torch.as_tensor(prev), torch.as_tensor(now), torch.as_tensor(r, dtype=torch.float32), angles)["pose"].numpy()

    run = drive_rectangle(est, np.array([0.4, 0.3, 0.0]), (1.2, 0.6), laps, seed, arena, sc, kidnap=kidnap)
    return run, np.hypot(*(run["est"][:, :2] - run["true"][:, :2]).T), mcl


def test_global_localisation_converges_from_a_uniform_prior():
    from tcn_ahrs.reproduce.kld_particle_filter import recovery_steps

    run, err, mcl = _arena_run(MclParams(), laps=1)
    assert mcl.counts[0] == MclParams().n_max          # the uniform prior over the free space
    assert recovery_steps(err, 0) < 50 and err[-100:].max() < 0.1
    assert max(mcl.counts[-100:]) < 200                # and KLD-sampling shrank the set


def test_recovery_after_kidnapping_with_random_injection():
    from tcn_ahrs.reproduce.kld_particle_filter import recovery_steps

    kid = (300, np.array([2.5, 1.5, 2.0]))
    _, err, _ = _arena_run(MclParams(alpha_slow=0.001, alpha_fast=0.1), kidnap=kid)
    assert err[301] > 1.0                               # carried away: the estimate is wrong
    assert recovery_steps(err, 301) is not None and err[-50:].max() < 0.1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_likelihood_on_cuda_equals_cpu():
    arena, sc = Arena(), Scanner()
    grid, res, origin = arena.grid()
    p = torch.rand(1000, 3) * torch.tensor([3.0, 2.0, 6.0]) - torch.tensor([0.0, 0.0, 3.0])
    r = torch.rand(sc.n_beams) * 3
    a = torch.as_tensor(sc.angles(), dtype=torch.float32)
    cpu = LikelihoodField(grid, res, origin, MclParams()).log_likelihood(p, r, a)
    gpu = LikelihoodField(grid, res, origin, MclParams(), device="cuda").log_likelihood(p.cuda(), r.cuda(), a.cuda())
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-3)


def test_reproduce_prints_the_reports_table(tmp_path, capsys):
    from tcn_ahrs.reproduce import papers, run

    assert "kld_particle_filter" in papers()
    cfg = {"name": "kld_particle_filter", "seed": 0, "laps": 2, "start": [0.4, 0.3, 0.0], "rectangle": [1.2, 0.6],
           "kidnap_laps": 1, "kidnap_step": 200, "kidnap_pose": [2.5, 1.5, 2.0], "cloud_step": 10,
           "alpha_slow": 0.001, "alpha_fast": 0.1, "scaling": [100, 1000], "threads": 1, "arena": {}, "scanner": {},
           "robot": {}, "filter": {}, "plots": True}
    res = run("kld_particle_filter", cfg, tmp_path)
    printed = capsys.readouterr().out
    for number in ("0.0324", "10.29", "127.82", "0.0514", "11.39", "42.71"):
        assert number in printed
    ev = res["evaluation"]
    assert ev["PF"]["particles"] == 200 and ev["KLD-PF"]["particles"] < 200
    assert ev["PF"]["position"] < 0.2 and ev["KLD-PF"]["position"] < 0.2
    assert (tmp_path / "plots" / "clouds.png").is_file() and (tmp_path / "plots" / "particles_and_kidnap.png").is_file()
    assert math.isfinite(res["scaling"]["rows"][1]["speedup_cpu"])
