"""How an IMU agrees with its ground truth: the frames, wiring, units and scale of the gyro and
accelerometer read against the attitude the ground truth says (what ``inspect_data`` shows and
:class:`~tcn_ahrs.sequence.ImuSequence` checks when a recording is built).
"""
from __future__ import annotations

from itertools import permutations, product
from typing import List, Optional

import numpy as np

from .conventions import GRAVITY

EXCITED_RATE = 10.0 * np.pi / 180.0  # rad/s, spread of the ground-truth rate about an axis
MIN_REPORTED_LAG_S = 0.02  # a fitted clock offset said from here (real datasets: 0-10 ms, one sample)
MIN_LAG_SAMPLES = 200  # turning samples needed to fit a clock offset (a still clip has none to read)
MIN_AXIS_R2 = 0.8  # share of an axis's reference signal the fitted map must explain to judge it
# ... about an axis the recording barely turns about (a phone held for texting: 4-8 °/s of spread
# about its y axis, with R² 0.84-0.90): a stricter share; on the 93 real recordings (BROAD, EuRoC,
# TUM VI, OxIOD, iPhones) such axes read their own sign, so a negated phone gyro axis is named. The
# mount rotation is fitted only where at least two axes are excited besides (a 3.5 s EuRoC tail that
# barely turns read a 6.7° mount from three quiet axes)
MIN_QUIET_AXIS_R2 = 0.85


def best_shift(w_gyro: np.ndarray, w_gt: np.ndarray, at: np.ndarray, most: int) -> int:
    """The shift d (samples, |d| <= ``most``) for which the gyro's rates ``w_gyro[at + d]`` (M, 3)
    agree best with the ground truth's ``w_gt`` (len(at), 3) (normalised correlation); 0 on a tie."""
    best, score0 = 0, -np.inf
    for d in sorted(range(-most, most + 1), key=abs):
        ok = (at + d >= 0) & (at + d < len(w_gyro))
        g, r = w_gyro[at[ok] + d], w_gt[ok]
        score = float((g * r).sum() / max(np.sqrt((g * g).sum() * (r * r).sum()), 1e-300))
        if score > score0 + 1e-9:
            best, score0 = d, score
    return best


def ground_truth_agreement(seq, lag_s: float = 0.05, min_rate: float = 0.2, max_offset_s: float = 0.1) -> dict:
    """How the IMU agrees with the ground truth of ``seq`` (shown by ``inspect_data``, checked
    when a recording is built):

    * ``angle_deg``: median angle between the mean gyro over ``lag_s`` and the body rate
      differentiated from the ground truth over the same interval, on samples where both turn
      faster than ``min_rate`` rad/s (``moving`` of them); a few degrees when frames agree;
      ``angle_deg_xyzw`` the same with the quaternions read as x,y,z,w;
    * ``scale``: median |ground-truth rate| / |gyro rate| (1 in rad/s; 0.017 for deg/s);
    * ``up``: mean direction (3,) of the specific force in the ground-truth frame (+z, ENU);
    * ``time_offset_s``: how late the ground truth's stamps run against the gyro's (fitted within
      ``max_offset_s``; the rates compared above are aligned by it).
    ``angle_deg``/``scale`` are None when fewer than 30 samples move."""
    import torch

    from . import so3

    valid = seq.quat_valid
    t = seq.time
    lag = max(1, int(round(lag_s * seq.rate)))
    ok = valid[lag:] & valid[:-lag]
    q = torch.as_tensor(np.where(valid[:, None], seq.quat, 0.0), dtype=torch.float64)
    a = torch.as_tensor(seq.accel[valid], dtype=torch.float64)
    qv = q[torch.as_tensor(valid)]
    # the specific force averaged in the ground-truth frame is gravity plus the mean linear
    # acceleration, Δv / T (a few cm/s² over a recording, even in fast translation): its direction
    # is up; averaging unit directions instead is pulled down by fast motion
    f_nav = so3.quat_rotate(qv, a)
    f = f_nav.mean(0)
    unit = f_nav / f_nav.norm(dim=1, keepdim=True).clamp_min(1e-9)
    out = {"up": (f / f.norm().clamp_min(1e-9)).numpy(), "angle_deg": None, "angle_deg_xyzw": None, "scale": None,
           "moving": 0, "accel_fit": None,
           # 1: the specific force keeps one direction in the ground-truth frame (a frame turned
           # as a whole); low: it scatters with the attitude (the accelerometer's own axes)
           "up_concentration": float(unit.mean(0).norm())}
    # the accelerometer per axis against the gravity the ground truth predicts in the body frame
    expected = so3.quat_rotate(so3.quat_conj(qv), torch.tensor([0.0, 0.0, GRAVITY], dtype=torch.float64).expand_as(a))
    out["accel_fit"] = axis_fit(a.numpy(), expected.numpy(), 0.0, 0.1 * GRAVITY, 1e-3, saturation=False, offset=False)
    out["accel_fit"]["static_problem"] = static_accel_problem(a.numpy(), expected.numpy(), seq.gyro[valid])
    if ok.sum() < 30:
        return out
    okt = torch.as_tensor(ok)
    span = torch.as_tensor(t[lag:] - t[:-lag])[okt][:, None]
    # mean gyro over (t_k, t_{k+lag}]: sample k moves the attitude from k-1 to k
    c = np.cumsum(np.vstack([np.zeros((1, 3)), seq.gyro[1:] * np.diff(t)[:, None]]), 0)
    w_gyro = torch.as_tensor((c[lag:] - c[:-lag]))[okt] / span

    def gt_rate(qq):
        return so3.quat_log(so3.quat_mul(so3.quat_conj(qq[:-lag][okt]), qq[lag:][okt])) / span

    w_gt = gt_rate(q)
    # a time offset between the IMU's and the ground truth's clocks first (a phone in a motion-capture
    # holder: 20-30 ms, whose rates then read as a 6-10° mount rotation): the shift of the gyro's
    # series that agrees best with the ground truth's rates; the mount is judged on what remains
    turning = (w_gt.norm(dim=1) > min_rate).numpy()
    shift = 0 if turning.sum() < MIN_LAG_SAMPLES else best_shift(
        np.asarray((c[lag:] - c[:-lag]) / (t[lag:] - t[:-lag])[:, None]), w_gt.numpy()[turning],
        np.flatnonzero(ok)[turning], max(1, int(round(max_offset_s * seq.rate))))
    out["time_offset_s"] = -shift * float(np.median(np.diff(t)))   # > 0: the ground truth's stamps run late
    sel = slice(None)
    # applied from MIN_REPORTED_LAG_S: a sample or two is within the fit's own resolution (the four
    # datasets fit 0-10 ms; a simulated 10° mount reads 1 sample and 0.3° less with it)
    if abs(out["time_offset_s"]) >= MIN_REPORTED_LAG_S:
        k = np.flatnonzero(ok)
        keep = (k + shift >= 0) & (k + shift < len(c) - lag)
        sel = torch.as_tensor(keep)
        w_gyro = torch.as_tensor(c[lag:] - c[:-lag])[k[keep] + shift] / span[sel]
        w_gt = w_gt[sel]
    # the constant part of gyro minus ground-truth rate: the gyro's bias (the median: a frozen or
    # clipped stretch is not a bias; a 5 s frozen gyro read as a 10 °/s "bias" with the mean)
    out["gyro_bias"] = (w_gyro - w_gt).median(0).values.numpy()
    out.update(axis_fit(w_gyro.numpy(), w_gt.numpy(), min_rate, EXCITED_RATE, 1e-4,  # needs only the ground truth to turn
                        quiet_r2=MIN_QUIET_AXIS_R2))
    moving = (w_gyro.norm(dim=1) > min_rate) & (w_gt.norm(dim=1) > min_rate)
    out["moving"] = int(moving.sum())
    if out["moving"] < 30:
        return out

    def angle(w):
        cos = torch.nn.functional.cosine_similarity(w[moving], w_gyro[moving], dim=1)
        return float(torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0))).median())

    out["angle_deg"] = angle(w_gt)
    out["angle_deg_xyzw"] = angle(gt_rate(q[:, [3, 0, 1, 2]])[sel])
    out["scale"] = float((w_gt[moving].norm(dim=1) / w_gyro[moving].norm(dim=1)).median())
    return out


def axis_fit(w_gyro: np.ndarray, w_gt: np.ndarray, min_rate: float, excited: float, floor: float,
              saturation: bool = True, offset: bool = True, quiet_r2: Optional[float] = None) -> dict:
    """Per-axis agreement of the gyro with the ground-truth body rate, on the samples where the
    ground truth turns (w_gt faster than ``min_rate``; the gyro may read anything there):

    * ``gyro_to_gt`` (3, 3): least-squares map ``w_gt ≈ A w_gyro + c`` (identity when wired right;
      ``c``, with ``offset``, takes up a constant bias);
      ``wiring``: the signed permutation nearest to it (which gyro axis reads which body axis);
      ``det``: its determinant's sign (−1: one axis flipped or two swapped, a left-handed frame);
      ``misalignment_deg``: the angle of the rotation nearest to ``A`` (a rotated body frame);
    * ``axis_r2``: per body axis, the share of its reference signal the map explains;
      ``judged_axes``: the excited axes with ``axis_r2`` ≥ :data:`MIN_AXIS_R2`, and, with
      ``quiet_r2``, the others with ``axis_r2`` ≥ it — the only ones whose wiring the checks
      judge (the evidence); ``rotation``: the rotation nearest to ``A``;
    * ``dead_axes``: gyro axes that read (almost) nothing while the ground truth turns about them;
    * ``saturated``: {axis: level} where the gyro sticks at its extreme while the ground truth
      turns faster."""
    moving = np.linalg.norm(w_gt, axis=1) > min_rate
    out = {"gyro_to_gt": None, "wiring": None, "det": None, "misalignment_deg": None, "dead_axes": [],
           "saturated": {}, "gt_moving": int(moving.sum()), "gt_scale": None, "excited_axes": [],
           "judged_axes": [], "axis_r2": None, "rotation": None}
    if moving.sum() < 30:
        return out
    g, r = w_gyro[moving], w_gt[moving]
    gt_spread = r.std(0)
    # dead: (almost) constant — below any sensor's noise (``floor``) and 50x below what the
    # ground truth predicts (a multicopter's accelerometer barely sees tilt, yet still reads noise)
    out["dead_axes"] = [k for k in range(3) if g[:, k].std() < min(0.02 * max(gt_spread[k], min_rate), floor)
                        and gt_spread[k] > max(min_rate / 2, 0.1 * excited)]
    for k in range(3 if saturation else 0):
        top = np.abs(g[:, k]).max()
        # saturated: the extreme value itself repeats (a clipped ADC), and the ground truth turns
        # faster about that axis there (a smooth peak has neither)
        stuck = np.abs(np.abs(g[:, k]) - top) <= 1e-6 * max(top, 1e-9)
        if top > 0 and stuck.mean() > 0.02 and np.median(np.abs(r[stuck, k])) > 1.2 * top:
            out["saturated"][k] = float(top)
    out["gt_scale"] = float(np.median(np.linalg.norm(r, axis=1) / np.maximum(np.linalg.norm(g, axis=1), 1e-12)))
    # how well each body axis is excited: the rotation is only identifiable about axes the
    # recording turns about (a trolley barely rolls or pitches)
    # (an axis counts when its rate spreads by more than 10 deg/s: OxIOD's trolleys roll and
    # pitch by 6-8 deg/s of vibration, too little to fit a rotation about those axes)
    out["excited_axes"] = [k for k in range(3) if gt_spread[k] > excited]
    # gyro: r ≈ a g + c, the offset c takes up a constant bias, which in a map through the origin
    # leaks into a as a false rotation (a simulated walk with a 5 deg/s bias read as a 16 deg mount).
    # Not for the accelerometer (offset=False): gravity is its signal's constant part, which an
    # offset would take from the map (a plugin's walk then read as miswired)
    if offset:
        sol = np.linalg.lstsq(np.column_stack([g, np.ones(len(g))]), r, rcond=None)[0]
        a, offset = sol[:3].T, sol[3]
    else:
        a, offset = np.linalg.lstsq(g, r, rcond=None)[0].T, np.zeros(3)
    # the evidence per body axis: how much of its reference signal the fitted map explains (R²).
    # An axis whose reference is noisier than its motion (a pendulum's motion-capture rates
    # about the axes it does not swing about: |correlation| ≤ 0.58 with the gyro) is not judged:
    # its row of the map is noise, and wiring, handedness and mount rotation read from it were
    # false refusals
    resid = r - g @ a.T - offset
    r2 = 1.0 - resid.var(0) / np.maximum(r.var(0), 1e-300)
    out["axis_r2"] = [float(x) for x in r2]
    # a quiet axis also needs a row that reads one axis at unit scale: with little spread the offset
    # takes up its mean and the slope is loose (a simulated walk's z: R² 0.99, slope 0.5)
    row = np.sort(np.abs(a), axis=1)
    clear = (row[:, 2] > 0.7) & (row[:, 2] < 1.4) & (row[:, 1] < 0.3)
    out["judged_axes"] = [k for k in range(3) if r2[k] >= MIN_AXIS_R2 and k in out["excited_axes"]
                          or quiet_r2 is not None and r2[k] >= quiet_r2 and clear[k]]
    # how much of the expected signal the map explains: judged only where it explains most (an
    # accelerometer in fast translation reads mostly its own motion, not gravity)
    out["explained"] = float(1.0 - (resid ** 2).sum() / max(((r - r.mean(0)) ** 2).sum(), 1e-12))
    out["gyro_to_gt"] = a
    perm = np.zeros((3, 3))
    used = set()
    for i in np.argsort(-np.abs(a).max(1)):  # strongest rows first
        j = max((j for j in range(3) if j not in used), key=lambda j: abs(a[i, j]))
        used.add(j)
        perm[i, j] = np.sign(a[i, j]) or 1.0
    out["wiring"] = perm
    out["det"] = float(np.sign(np.linalg.det(a)))
    u, _, vt = np.linalg.svd(a)
    rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    out["misalignment_deg"] = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
    out["rotation"] = rot  # C_body_from_imu nearest to the map: what gt_body_from_imu declares
    return out


def signed_permutations():
    """The 48 signed permutation matrices W (3, 3) — every way three axes can be wired, swapped or
    negated — each with its key (W as a tuple of int tuples)."""
    for perm in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            w = np.zeros((3, 3))
            w[range(3), perm] = signs
            yield tuple(map(tuple, w.astype(int))), w


def mag_wiring_fit(mag: np.ndarray, quat: np.ndarray, valid: np.ndarray, step: Optional[int] = None) -> dict:
    """The magnetometer's axes against the ground truth: for each of the 48 signed permutations W,
    least squares of ``R_k W^T m_k = m_nav + R_k h`` (a constant field in the navigation frame and
    a constant body-frame offset ``h``; R_k = nav_from_body). ``residual`` {W as a tuple: RMS µT};
    ``best``: the W that fits best, ``identity`` / ``best_rms``: the RMS of W = I and of the best,
    ``offset``: h of W = I (µT), ``field``: m_nav of W = I, ``identity_no_offset``: the RMS of
    W = I without the offset. ``step``: every step-th sample (default: about 4000 of them)."""

    import torch

    from . import so3

    ok = np.asarray(valid, dtype=bool) & (np.linalg.norm(mag, axis=1) > 0)
    idx = np.flatnonzero(ok)[::max(1, step if step is not None else len(mag) // 4000)]
    out = {"best": None, "identity": None, "best_rms": None, "offset": None, "field": None, "n": int(idx.size)}
    if idx.size < 30:
        return out
    r = so3.quat_to_matrix(torch.as_tensor(quat[idx], dtype=torch.float64)).numpy()  # (n, 3, 3) nav_from_body
    m = np.asarray(mag, dtype=np.float64)[idx]
    design = np.concatenate([np.broadcast_to(np.eye(3), r.shape), -r], axis=2).reshape(-1, 6)
    fits = {}
    for key, w in signed_permutations():                             # imu reading = W body
        y = np.einsum("nij,nj->ni", r, m @ w).reshape(-1)            # R W^T m  (W^T m = m @ W)
        sol, *_ = np.linalg.lstsq(design, y, rcond=None)
        fits[key] = (float(np.sqrt(np.mean((y - design @ sol) ** 2))), sol)
    eye = tuple(map(tuple, np.eye(3, dtype=int)))
    best = min(fits, key=lambda k: fits[k][0])
    # as wired, without the offset: how much of the residual a constant body-frame offset explains
    y = np.einsum("nij,nj->ni", r, m).reshape(-1)
    sol0, *_ = np.linalg.lstsq(design[:, :3], y, rcond=None)
    out["identity_no_offset"] = float(np.sqrt(np.mean((y - design[:, :3] @ sol0) ** 2)))
    out.update(best=np.array(best, dtype=float), identity=fits[eye][0], best_rms=fits[best][0],
               offset=fits[eye][1][3:], field=fits[eye][1][:3])
    return out


def static_accel_problem(acc: np.ndarray, expected: np.ndarray, gyro: np.ndarray) -> Optional[str]:
    """The accelerometer's axes against the gravity the ground truth predicts, on the still samples
    (norm within 5 % of g, turning slower than 0.5 rad/s: little motion besides gravity), or None.
    Named where another signed permutation of its columns fits them twice as well as the columns as
    given (and by 0.5 m/s² more), on at least 500 such samples: a phone held for texting barely
    tilts, so its x/y swap is too small a signal for the per-axis fit (its inclination 8.1° against
    1.0°; as given 1.51 m/s², swapped back 0.64). The 81 real recordings with that many still samples
    fit best as given or within 1 % of it."""
    still = (np.abs(np.linalg.norm(acc, axis=1) - GRAVITY) < 0.05 * GRAVITY) & (np.linalg.norm(gyro, axis=1) < 0.5)
    if still.sum() < 500:
        return None
    a, e = acc[still], expected[still]
    rms = {key: float(np.sqrt(np.mean(np.sum((a @ w.T - e) ** 2, 1)))) for key, w in signed_permutations()}
    given, best = rms[tuple(map(tuple, np.eye(3, dtype=int)))], min(rms, key=rms.get)
    if not (given > 2.0 * rms[best] and given - rms[best] > 0.5):
        return None
    return (f"axes wired differently from the ground truth's body frame: on its {int(still.sum())} still samples the "
            f"gravity it predicts is read as acc = {[[int(x) for x in r] for r in best]} body ({rms[best]:.2f} m/s² RMS; as wired "
            f"{given:.2f}): fix the accelerometer's columns")


def mag_wiring_problem(fit: dict) -> Optional[str]:
    """The magnetometer's axes against the ground truth (``fit``: :func:`mag_wiring_fit`'s), or None: named
    where another signed permutation of its columns keeps the field constant in the navigation
    frame far better than the columns as given (a 3 times smaller residual, > 5 uT as given:
    BROAD's trials fit 0.8-16 uT as given, and where one permutation is clearly best it is the
    identity; a trial that barely turns ties several)."""
    if fit["best"] is None or np.array_equal(fit["best"], np.eye(3)):
        return None
    if not (fit["identity"] > 5.0 and fit["identity"] > 3.0 * fit["best_rms"]):
        return None
    w = fit["best"].astype(int)
    hand = ", a left-handed frame (one axis negated or two swapped)" if np.linalg.det(w) < 0 else ""
    return (f"axes wired differently from the gyro's and the ground truth's body frame{hand}: read as "
            f"mag = {w.tolist()} body, the field stays constant in the navigation frame to {fit['best_rms']:.1f} uT, "
            f"as wired to {fit['identity']:.1f} uT: fix the magnetometer's columns")


def evidence_text(fit: dict) -> str:
    """Which axes a wiring verdict rests on: ``judged x, z (R² 0.99, 0.97); not judged: y (R² 0.31)``."""
    r2, judged = fit.get("axis_r2") or [float("nan")] * 3, set(fit.get("judged_axes") or [])
    yes = [k for k in range(3) if k in judged]
    no = [k for k in range(3) if k not in judged]
    text = "judged " + ", ".join("xyz"[k] for k in yes) + " (R² " + ", ".join(f"{r2[k]:.2f}" for k in yes) + ")"
    if no:
        text += "; not judged (too little motion or a noisier reference): " + ", ".join(
            f"{'xyz'[k]} (R² {r2[k]:.2f})" for k in no)
    return text




def lag_text(agree: dict) -> str:
    lag = agree.get("time_offset_s") or 0.0
    return f", after a time offset of {1000 * lag:.0f} ms fitted first" if abs(lag) >= MIN_REPORTED_LAG_S else ""
