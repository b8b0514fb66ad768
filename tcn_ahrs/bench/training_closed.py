"""The training section's step for the shipped recipe (the learned closed loop), and its variants."""
from __future__ import annotations

import time
from typing import Any, Dict

import torch

from .common import Threads


CLOSED_VARIANTS = ("eager", "tensor_scan", "threads1", "bf16", "compile")


def closed_loop_step(variant: str, p: Dict[str, Any], device: str, seed: int, module, model, store, opt):
    """The shipped recipe's step (:meth:`tcn_ahrs.training.run.AHRSModule._closed_loop_step`, experiment
    broad9_cl): B streams x one chunk of ``window`` samples after ``receptive_field - 1`` samples
    of context; the calibration networks over all of it (float32), the closed loop over the chunk,
    :func:`~tcn_ahrs.losses.attitude_loss`, backward, AdamW. Variants: ``eager`` (the recipe: on
    the CPU the loop and its reverse pass compiled, float64 inside,
    :class:`~tcn_ahrs.model.closed_loop_compiled.ScanFunction`), ``tensor_scan`` (the loop as tensor
    ops under autograd, as before: ``backend="torch"``), ``threads1`` (one torch thread), ``bf16``
    (the networks under bfloat16 autocast; filter and loss in float32), ``compile`` (torch.compile
    of the networks)."""
    from ..data import augment
    from ..losses import attitude_loss

    if variant not in CLOSED_VARIANTS:
        raise ValueError(f"closed-loop training variant {variant!r}: expected one of {CLOSED_VARIANTS}")
    B, L = int(p["batch_size"]), int(p["window"])
    ctx = int(model.receptive_field) - 1
    noise = {"gyro": 0.001, "acc": 0.01, "mag": 0.1}
    n_store = store["imu"].shape[0]
    gen = torch.Generator(device="cpu").manual_seed(seed)
    arange = torch.arange(L + ctx, device=device)
    calibrate = torch.compile(model.calibration) if variant == "compile" else model.calibration
    if variant == "tensor_scan":
        model.closed.backend = "torch"

    def body():
        starts = torch.randint(0, n_store - L - ctx + 1, (B,), generator=gen).to(device)
        w = {k: v[starts[:, None] + arange] for k, v in store.items()}
        imu = augment(w["imu"], noise)
        if variant == "bf16":
            with torch.autocast(torch.device(device).type, dtype=torch.bfloat16):
                cal = calibrate(imu)
            cal = {k: v.float() for k, v in cal.items()}
        else:
            cal = calibrate(imu)
        out = model.closed.run(cal, imu, w["dt"], w["rot"][:, ctx], torch.zeros(B, 3, device=device), None, ctx,
                               imu.dtype)
        valid = w["valid"][:, ctx:].clone()
        valid[:, 0] = False
        loss = attitude_loss(out["rot"], w["rot"][:, ctx:], valid, float(module.hparams.attitude_delta))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss

    def step():
        if variant == "threads1":
            with Threads(1):
                return body()
        return body()

    info: Dict[str, Any] = {"variant": variant, "compile_s": None}
    if variant == "compile":
        t = time.perf_counter()
        step()
        step()
        info["compile_s"] = time.perf_counter() - t
    return step, info
