"""Calibration faults a recording shows: a gyro bias beyond what the filters estimate, an
accelerometer bias, hard and soft iron — each fitted (against the ground truth where there is one,
from the field's norm alone for hard iron) and named with its size and the declaration that fixes it
(warnings when a recording is built: :class:`~tcn_ahrs.sequence.ImuSequence`). How often each fires on
the project's real recordings, clean and with the fault: ``python scripts/calibration_faults.py``.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from .conventions import GRAVITY


def hard_iron_fit(mag: np.ndarray) -> dict:
    """The magnetometer's constant offset (hard iron) from the field's norm alone, no ground truth:
    least squares of |m − h|² = r² over the recording (a sphere through the readings). ``offset``
    (3,) µT, ``radius`` µT, ``spread_before`` / ``spread_after``: the norm's relative spread
    (std / mean) of the raw readings and with the offset removed, ``coverage``: the smallest
    spread of the readings' directions over an axis (0: one direction only; the offset along an
    axis the recording never turns about is not identifiable), all None below 30 samples."""
    m = np.asarray(mag, dtype=np.float64)
    out = {"offset": None, "radius": None, "spread_before": None, "spread_after": None, "coverage": 0.0}
    ok = np.linalg.norm(m, axis=1) > 0
    m = m[ok]
    if len(m) < 30:
        return out
    # |m|² = 2 m·h + (r² − |h|²): linear in (h, c)
    sol = np.linalg.lstsq(np.column_stack([2.0 * m, np.ones(len(m))]), (m * m).sum(1), rcond=None)[0]
    h = sol[:3]
    r = float(np.sqrt(max(sol[3] + h @ h, 0.0)))
    n0, n1 = np.linalg.norm(m, axis=1), np.linalg.norm(m - h, axis=1)
    u = (m - h) / np.maximum(n1, 1e-12)[:, None]
    out.update(offset=h, radius=r, spread_before=float(n0.std() / max(n0.mean(), 1e-12)),
               spread_after=float(n1.std() / max(n1.mean(), 1e-12)),
               coverage=float(np.sqrt(max(np.linalg.eigvalsh(np.cov(u.T))[0], 0.0))))
    return out


def plane_hard_iron_fit(mag: np.ndarray) -> Optional[dict]:
    """The magnetometer's offset in the plane a recording turns in, from the field's norm alone: a
    phone held for texting turns about its z axis only, so the readings trace a circle whose centre
    (x, y) is the offset there, and the z component stays as recorded (0 here). The plane: the
    directions along which the readings spread by more than 0.3 × the largest spread (offset-free:
    the covariance of the raw readings). ``{"offset": (3,) µT, "radius": the norm with it removed µT
    (median), "spread_before" / "spread_after": the norm's standard deviation µT}``, or None (below 30
    samples, or fewer than two such directions)."""
    m = np.asarray(mag, dtype=np.float64)
    m = m[np.linalg.norm(m, axis=1) > 0]
    if len(m) < 30:
        return None
    w, v = np.linalg.eigh(np.cov(m.T))
    sd = np.sqrt(np.maximum(w, 0.0))
    plane = v[:, sd > 0.3 * sd.max()]
    if plane.shape[1] < 2:
        return None
    q = m @ plane    # |q − c|² = r²: linear in (c, r² − |c|²)
    sol = np.linalg.lstsq(np.column_stack([2.0 * q, np.ones(len(q))]), (q * q).sum(1), rcond=None)[0]
    h = plane @ sol[:-1]
    n0, n1 = np.linalg.norm(m, axis=1), np.linalg.norm(m - h, axis=1)
    return {"offset": h, "radius": float(np.median(n1)), "spread_before": float(n0.std()),
            "spread_after": float(n1.std())}


def judged_hard_iron(mag: np.ndarray) -> Optional[tuple]:
    """A magnetometer's constant offset (hard iron: a magnet or steel on the device, an uncalibrated
    sensor) found from the field's norm alone (:func:`hard_iron_fit`): ``(offset (3,) µT, what was
    found in words)``, or None. Judged where the recording turns about every axis, the offset is
    large against the field (> 30 % of it) and removing it makes the norm constant (its spread
    halved, and below 5 %) — a field that moves with the body is a disturbance the filters reject,
    an offset is not (BROAD's attached magnets: their spread does not fall; its translation trials
    turn too little to fit a sphere: the spread grows). Where the recording turns about one axis only
    (a phone held for texting), the offset in the plane it turns in (:func:`plane_hard_iron_fit`) is
    judged instead: over half the field, and the norm's spread below 0.3 × the raw one. On the 84 real
    recordings with a magnetometer, whole and as two 45 s clips each (252), none clean fires; with
    150 µT added on x 87 do (the sphere alone: 51), with (60, −40, 30) µT 99 (61): the iPhone 4S held
    for texting, as the fault trial's clip, goes from 75.9° to 5.3° with the default (clean 2.7°).
    """
    fit = hard_iron_fit(mag)
    if fit["offset"] is None:
        return None
    if fit["coverage"] < 0.1:
        plane = plane_hard_iron_fit(mag)
        if plane is None:
            return None
        h, r = plane["offset"], plane["radius"]
        if not (plane["spread_after"] < 0.3 * plane["spread_before"] and float(np.linalg.norm(h)) > 0.5 * r):
            return None
        return h, (f"a constant offset of {[round(float(v), 1) for v in h]} uT in the plane the recording turns in "
                   f"(hard iron: the field's norm varies by {plane['spread_before']:.1f} uT, by {plane['spread_after']:.1f} "
                   f"uT with it removed; field {r:.1f} uT; the axis it never turns about is left as recorded)")
    h, r = fit["offset"], fit["radius"]
    if not (fit["spread_after"] < min(0.05, 0.5 * fit["spread_before"]) and float(np.linalg.norm(h)) > 0.3 * r):
        return None
    hx = [round(float(v), 1) for v in h]
    return h, (f"a constant offset of {hx} uT (hard iron: the field's norm varies by {100 * fit['spread_before']:.0f} %, "
               f"by {100 * fit['spread_after']:.0f} % with it removed; field {r:.1f} uT)")


ACC_BIAS_NAMED = 0.35  # m/s²: the accelerometer bias named from here (clean real recordings: ≤ 0.26)
ACC_BIAS_MAX_SE = 0.08  # m/s²: ... where the fit reads it this well (the device turned while nearly still)


def accel_bias_fit(seq, window_s: float = 1.0) -> Optional[dict]:
    """The accelerometer's constant bias against the gravity the ground truth predicts: per window
    of ``window_s``, the mean specific force turned into the navigation frame minus gravity is
    ``mean(R) b + ε − mean(R [e]×) δ`` plus the window's mean acceleration (velocity change over
    the window: noise), with ``b`` the body-frame bias, ``ε`` a navigation-frame offset (the ground
    truth's vertical tilted, a scale on gravity) and ``δ`` a small mount rotation (e = Rᵀ g up);
    least squares over the windows. ``{"bias": (3,) m/s², "se": (3,) its standard errors from the
    residual, "windows": n}``, or None below 10 windows. A device that never turns (a phone held
    for texting, a trolley) leaves ``b``, ``ε`` and ``δ`` confounded: large ``se``."""
    import torch

    from . import so3

    n = max(int(round(window_s * seq.rate)), 2)
    k = len(seq.time) // n
    ok = seq.quat_valid[:n * k].reshape(k, n).all(1)
    if int(ok.sum()) < 10:
        return None
    q = np.where(seq.quat_valid[:n * k, None], seq.quat[:n * k], np.array([1.0, 0.0, 0.0, 0.0]))
    r = so3.quat_to_matrix(torch.as_tensor(q, dtype=torch.float64)).numpy()       # nav_from_body
    e = r[:, 2, :] * GRAVITY                                                       # gravity's specific force, body
    e_x = np.zeros((len(e), 3, 3))
    e_x[:, 0, 1], e_x[:, 0, 2], e_x[:, 1, 2] = -e[:, 2], e[:, 1], -e[:, 0]
    e_x = e_x - np.transpose(e_x, (0, 2, 1))
    y = np.einsum("nij,nj->ni", r, seq.accel[:n * k]) - np.array([0.0, 0.0, GRAVITY])

    def mean(a):
        return a.reshape((k, n) + a.shape[1:]).mean(1)[ok]

    x = np.concatenate([mean(r), np.broadcast_to(np.eye(3), (int(ok.sum()), 3, 3)),
                        -mean(np.einsum("nij,njk->nik", r, e_x))], 2).reshape(-1, 9)
    yy = mean(y).reshape(-1)
    sol, *_ = np.linalg.lstsq(x, yy, rcond=None)
    res = yy - x @ sol
    cov = float(res @ res) / max(len(yy) - 9, 1) * np.linalg.pinv(x.T @ x)
    return {"bias": sol[:3], "se": np.sqrt(np.maximum(np.diag(cov)[:3], 0.0)), "windows": int(ok.sum())}


def soft_iron_fit(mag: np.ndarray, quat: np.ndarray, valid: np.ndarray) -> Optional[dict]:
    """The magnetometer's soft iron against the ground truth: least squares of
    ``R_k ((I + E) m_k − c) = m_nav`` (E traceless: the field's scale is not the sensor's) against the
    offset-only fit (E = 0, :func:`mag_wiring_fit`'s model as wired). ``{"distortion": E (3, 3),
    "offset": (I + E)⁻¹ c µT (the hard iron before it), "rms": µT, "rms_offset_only": µT, "norm": the
    readings' median norm µT}``, or None below 100 samples."""
    import torch

    from . import so3

    ok = np.asarray(valid, dtype=bool) & (np.linalg.norm(mag, axis=1) > 0)
    idx = np.flatnonzero(ok)[::max(1, int(ok.sum()) // 4000)]
    if idx.size < 100:
        return None
    r = so3.quat_to_matrix(torch.as_tensor(quat[idx], dtype=torch.float64)).numpy()
    m = np.asarray(mag, dtype=np.float64)[idx]
    # unknowns: E (8: traceless), c (3), m_nav (3); R E m − R c − m_nav = −R m
    basis = [np.outer(np.eye(3)[i], np.eye(3)[j]) for i in range(3) for j in range(3) if (i, j) != (2, 2)]
    basis = [b - (b[0, 0] + b[1, 1]) * np.diag([0.0, 0.0, 1.0]) if b[0, 0] + b[1, 1] else b for b in basis]
    cols = [np.einsum("nab,bc,nc->na", r, b, m) for b in basis]
    cols += [-r[:, :, i] for i in range(3)] + [-np.broadcast_to(np.eye(3)[i], (len(idx), 3)) for i in range(3)]
    x, y = np.stack(cols, 2).reshape(-1, 14), -np.einsum("nab,nb->na", r, m).reshape(-1)
    sol, *_ = np.linalg.lstsq(x, y, rcond=None)
    sol0, *_ = np.linalg.lstsq(x[:, 8:], y, rcond=None)
    distortion = sum(v * b for v, b in zip(sol[:8], basis))
    return {"distortion": distortion, "offset": np.linalg.solve(np.eye(3) + distortion, sol[8:11]),
            "rms": float(np.sqrt(np.mean((y - x @ sol) ** 2))),
            "rms_offset_only": float(np.sqrt(np.mean((y - x[:, 8:] @ sol0) ** 2))),
            "norm": float(np.median(np.linalg.norm(m, axis=1)))}


GYRO_BIAS_CLIP = np.radians(2.0)
"""rad/s: the largest gyro bias VQF's defaults (and the backbone's, the default) estimate in motion."""


def accel_bias_note(fit: Optional[dict]) -> Optional[str]:
    """An accelerometer bias (``fit``: :func:`accel_bias_fit`'s) named on the axes the fit reads well
    (standard error ≤ :data:`ACC_BIAS_MAX_SE`) where it exceeds :data:`ACC_BIAS_NAMED` there by three
    standard errors: on the 93 real recordings, whole and as two 45 s clips each (279), none clean is
    named (the largest clean reading, less three standard errors: 0.26 m/s²); with 0.5 m/s² added to
    every axis 48 are (BROAD's rotations, phones held up while walking: a device that turns while
    nearly still); the others turn too little to tell a bias from a mount (a phone held for texting)."""
    if fit is None:
        return None
    b, se = fit["bias"], fit["se"]
    read = se <= ACC_BIAS_MAX_SE
    if not (read.any() and np.linalg.norm(b[read]) > ACC_BIAS_NAMED + 3.0 * se[read].max()):
        return None
    unread = " and ".join(a for a, r in zip("xyz", read) if not r)
    told = "" if read.all() else f" ({unread}: this recording cannot tell a bias there from a mount; given as 0)"
    return (f"field 'acc': a constant bias of {np.round(np.where(read, b, 0.0), 2).tolist()} m/s²{told} "
            f"(± {se[read].max():.2f}) against the gravity the ground truth predicts (fitted over {fit['windows']} "
            "windows of 1 s beside the mount and the ground truth's vertical): declare acc_bias: "
            f"{np.round(np.where(read, b, 0.0), 3).tolist()} (m/s², subtracted), or let `tcn-ahrs search` fit it "
            "(its full calibration)")


def soft_iron_note(fit: Optional[dict]) -> Optional[str]:
    """Soft iron (``fit``: :func:`soft_iron_fit`'s) named where the distortion explains the field:
    its residual under 60 % of the offset-only fit's and under 5 % of the readings' median norm (the
    offset-only fit's field shrinks with the distortion: a phone held for texting), with a plausible
    distortion (its largest eigenvalue 0.05-0.75; a larger one absorbs a disturbance: BROAD's attached
    magnet 1 cm fits 0.79). On the 84 real recordings with a magnetometer, whole and as 45 s clips
    (252), none clean is named; with the fault trial's soft iron (1.3 / 0.8 / 1.1, 0.2 coupling) 75
    are (the rest turn too little, or their field is disturbed)."""
    if fit is None:
        return None
    e = float(np.abs(np.linalg.eigvalsh(0.5 * (fit["distortion"] + fit["distortion"].T))).max())
    if not (0.05 < e < 0.75 and fit["rms"] < 0.6 * fit["rms_offset_only"] and fit["rms"] < 0.05 * fit["norm"]):
        return None
    soft = np.round(np.eye(3) + fit["distortion"], 3).tolist()
    return (f"field 'mag': soft iron fixed in the body (the field scaled by up to {100 * e:.0f} % along one axis; it stays "
            f"constant to {fit['rms']:.1f} uT with it removed, {fit['rms_offset_only']:.1f} uT without): declare "
            f"mag_soft_iron: {soft} and mag_hard_iron: {np.round(fit['offset'], 1).tolist()}, or let `tcn-ahrs search` "
            "fit it (its full calibration: the magnetometer's ellipsoid)")


def calibration_notes(agree: dict, mag_fit: Optional[dict], declared, accel: Optional[dict] = None,
                      soft: Optional[dict] = None) -> List[str]:
    """Calibration faults the ground truth shows, each with its size and the fix (warnings: the
    recording is usable, the filter will do worse than it could):

    * a gyro bias beyond what the filter estimates in motion (:data:`GYRO_BIAS_CLIP`): the median
      of gyro minus ground-truth rate over the recording (the iPhone 5: (+5.4, −0.9, +0.7) °/s, EuRoC's
      MAV: (−0.1, +1.2, +4.4) °/s; BROAD, TUM VI, OxIOD, iPhone 4S: under 1 °/s);
    * a magnetometer offset (hard iron) fixed in the body: the offset of ``mag_fit``
      (:func:`mag_wiring_fit`, None without a magnetometer: a constant field in the navigation frame)
      where it is larger than half the field and
      explains most of the residual (as wired, with the offset: under 30 % of the residual without
      it; the 78 real recordings with a magnetometer fit 0.01-1.2 times the field, their residual
      at least 45 % of the one without; a 150 µT offset on a phone: 3.3 times, 2.5 %).
    * an accelerometer bias (``accel``: :func:`accel_bias_fit`'s, :func:`accel_bias_note`) and soft
      iron (``soft``: :func:`soft_iron_fit`'s, :func:`soft_iron_note`).
    ``declared``: the recording's declarations (a declared ``gyr_bias`` / ``mag_hard_iron`` /
    ``acc_bias`` / ``mag_soft_iron`` is not named again)."""
    notes = [n for n, key in ((accel_bias_note(accel), "acc_bias"), (soft_iron_note(soft), "mag_soft_iron"))
             if n and key not in declared]
    bias = agree.get("gyro_bias")
    if bias is not None and "gyr_bias" not in declared and np.abs(bias).max() > GYRO_BIAS_CLIP:
        b = [round(float(v), 4) for v in bias]
        notes.append(f"field 'gyro': a constant bias of {np.round(np.degrees(bias), 1).tolist()} °/s against the "
                     f"ground truth, beyond the {np.degrees(GYRO_BIAS_CLIP):g} °/s the filters estimate in motion (VQF's "
                     f"clip): declare gyr_bias: {b} (rad/s, subtracted), or let `tcn-ahrs search` fit it (its "
                     "gyro_bias calibration); the default's causal check takes it only from the recording's rests")
    if mag_fit is not None and mag_fit["offset"] is not None and "mag_hard_iron" not in declared:
        h, field = mag_fit["offset"], float(np.linalg.norm(mag_fit["field"]))
        if np.linalg.norm(h) > 0.5 * field and mag_fit["identity"] < 0.3 * mag_fit["identity_no_offset"]:
            notes.append(f"field 'mag': a constant offset of {np.round(-h, 1).tolist()} uT fixed in the body "
                         f"(hard iron: {np.linalg.norm(h) / field:.1f} times the {field:.0f} uT field; the field stays "
                         f"constant to {mag_fit['identity']:.1f} uT with it removed, {mag_fit['identity_no_offset']:.1f} uT "
                         f"without): declare mag_hard_iron: {np.round(-h, 1).tolist()}")
    return notes
