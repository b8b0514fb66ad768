"""The C99 runtime generated from a checkpoint (tcn_ahrs.export.c): its backbone is the
kernel's own source translated (equal to the Python kernel), the whole runtime gives what the
numba streaming runtime gives over whole recordings, refuses bad samples before its state
changes, and the CSV example builds and streams."""

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tcn_ahrs.conventions import MIN_DT
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.export.c import kernel_c
from tcn_ahrs.export.c.runtime import WIDE_KERNELS, template
from tcn_ahrs.export.c import CRuntime, compile_c, export_c, generate_c
from tcn_ahrs.export.inputs import ExportError
from tcn_ahrs.filters import backbone as bb
from tcn_ahrs.kernels import backbone as K

ROOT = Path(__file__).resolve().parents[1]
CKPTS = ROOT / "checkpoints"
# ../shared beside the checkout (a git worktree one level deeper: ../../shared)
BROAD = next((p / "shared" / "datasets" / "broad" for p in (ROOT.parent, ROOT.parent.parent)
              if (p / "shared" / "datasets" / "broad").is_dir()), ROOT.parent / "shared" / "datasets" / "broad")
CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler")
TOL = 1e-4  # rad: the C runtime (float or double build) against BackboneStreaming
# the shipped checkpoints the C runtime is checked on: broad9/broad6 (both networks off under
# their knobs: the backbone alone), oxiod9/euroc6 (both networks on), tumvi6 (the trust net only)
NAMES = ("broad9", "broad6", "oxiod9", "euroc6", "tumvi6")
# where each lives: the search shipped a closed loop (euroc6) and classical filters (tumvi6, oxiod9)
# under those names; their residual models stay in checkpoints/residual/
PATHS = {n: CKPTS / f"{n}_residual.ckpt" if n.startswith("broad") else CKPTS / "residual" / f"{n}.ckpt" for n in NAMES}


def _axes(name):
    return 9 if name.endswith("9") else 6


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between (N, 4) quaternions, exact near zero (atan2 of conj(a) b)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    w = aw * bw + ax * bx + ay * by + az * bz
    x = aw * bx - ax * bw - ay * bz + az * by
    y = aw * by + ax * bz - ay * bw - az * bx
    z = aw * bz - ax * by + ay * bx - az * bw
    return 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), np.abs(w))


def _imu(seq, axes):
    return np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1).astype(np.float32)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """name -> (CRuntime of the double build, the model's BackboneStreaming, generated paths)."""
    from tcn_ahrs.checkpoint import model_from_checkpoint

    pytest.importorskip("numba")
    from tcn_ahrs.streaming import BackboneStreaming

    if CC is None:
        pytest.skip("no C compiler")
    out = tmp_path_factory.mktemp("c_runtime")
    libs = {}
    for name in NAMES:
        paths = export_c(PATHS[name], out, name)
        so = compile_c(paths["c"], out / f"lib{name}.so", "double", CC)
        stream = BackboneStreaming(model_from_checkpoint(PATHS[name]))
        stream.chunk_networks = 1 << 30  # the networks per sample, as the C runtime
        libs[name] = (CRuntime(so, name, _axes(name)), stream, paths)
    return libs


@pytest.fixture(scope="module")
def runtimes(built, tmp_path_factory):
    """(name, real) -> (CRuntime, BackboneStreaming): the double build and the float build
    (-DTCN_AHRS_REAL=float: float arithmetic, the low-pass filters and the heading update in
    double) of each checkpoint."""
    out = tmp_path_factory.mktemp("c_runtime_float")
    rts = {}
    for name, (c_rt, stream, paths) in built.items():
        rts[name, "double"] = (c_rt, stream)
        so = compile_c(paths["c"], out / f"lib{name}_float.so", "float", CC)
        rts[name, "float"] = (CRuntime(so, name, _axes(name)), stream)
    return rts


def _compare(c_rt, stream, imu, dt, q0):
    q0 = np.asarray(q0, dtype=np.float32)  # both runtimes from the same float32 inputs
    c_rt.reset(q0)
    code, out = c_rt.run(imu, dt)
    assert code == 0
    q_ref, w_ref = stream.run(imu.astype(np.float64), float(dt), np.asarray(q0, dtype=np.float64))
    return float(_angle(out[:, :4].astype(np.float64), q_ref).max()), float(np.abs(out[:, 4:] - w_ref).max())


# ------------------------------------------------------------------ the backbone alone
DRIVER = r"""
void bb_run(const double *p, double *s, const double *g, const double *a, const double *m, const double *dt,
            const double *ta, const double *tm, const double *tb, int n, int use_mag, double *q, double *f)
{
    double c[%(N_COEFF)d], last = -1.0;
    int i;
    for (i = 0; i < n; i++) {
        if (dt[i] != last) { bb_coefficients(p, dt[i], c); last = dt[i]; }
        bb_gyro_update(s, p, c, g[3 * i], g[3 * i + 1], g[3 * i + 2]);
        if (a[3 * i] != 0.0 || a[3 * i + 1] != 0.0 || a[3 * i + 2] != 0.0)
            bb_acc_update(s, p, c, a[3 * i], a[3 * i + 1], a[3 * i + 2], ta[i], tb[i]);
        if (use_mag && (m[3 * i] != 0.0 || m[3 * i + 1] != 0.0 || m[3 * i + 2] != 0.0))
            bb_mag_update(s, p, c, m[3 * i], m[3 * i + 1], m[3 * i + 2], tm[i]);
        if (use_mag) bb_quat9(s, q + 4 * i, q + 4 * i + 1, q + 4 * i + 2, q + 4 * i + 3);
        else bb_quat6(s, q + 4 * i, q + 4 * i + 1, q + 4 * i + 2, q + 4 * i + 3);
        f[6 * i] = s[%(S_BIAS)d]; f[6 * i + 1] = s[%(S_BIAS)d + 1]; f[6 * i + 2] = s[%(S_BIAS)d + 2];
        f[6 * i + 3] = s[%(S_REST)d]; f[6 * i + 4] = s[%(S_MAGDIST)d]; f[6 * i + 5] = s[%(S_DELTA)d];
    }
}
"""


@needs_cc
def test_the_translated_backbone_equals_the_python_kernel(tmp_path):
    """kernels/backbone.py translated to C (tcn_ahrs.export.c.translate) steps as the kernel does
    (numba, float64), on every path: varying dt, trusts, rest, magnetic rejection, both
    settings of the parameter branches."""
    import ctypes as ct

    src, _ = kernel_c(K, "bb_", ("coefficients", "gyro_update", "acc_update", "mag_update", "quat6", "quat9"),
                      WIDE_KERNELS)
    code = "#include <math.h>\n" + template("helpers.h.in") + src + DRIVER % {"N_COEFF": K.N_COEFF, "S_BIAS": K.S_BIAS,
                                                             "S_REST": K.S_REST, "S_MAGDIST": K.S_MAGDIST,
                                                             "S_DELTA": K.S_DELTA}
    (tmp_path / "bb.c").write_text(code)
    lib = ct.CDLL(compile_c(tmp_path / "bb.c", tmp_path / "libbb.so", "double", CC))
    seq = simulate("walking", 40.0, 100.0, seed=5, axes=9, mag_disturbances_per_minute=3)
    n = seq.gyro.shape[0]
    rng = np.random.default_rng(0)
    dt = np.where(rng.random(n) < 0.1, 0.012, 0.01)  # coefficients recomputed when dt changes
    acc = seq.accel.copy()
    acc[100:105] = 0.0  # skipped, as VQF
    trusts = [rng.uniform(0.0, 2.0, n) for _ in range(3)]
    dbl = ct.POINTER(ct.c_double)
    for params, use_mag in ((K.BackboneParams(), True), (K.BackboneParams(), False),
                            (K.BackboneParams(mag_current_tau=0.0, rest_bias=0.0), True),
                            (K.BackboneParams(motion_bias=0.0, mag_rejection=0.0), True),
                            (K.BackboneParams(rest_check=1.0), True)):
        q0 = np.array([0.9, 0.1, -0.2, 0.3])
        # the causal device check (rest_check) takes a bias beyond VQF's clip: 4 °/s about z
        gyro = seq.gyro + (np.radians([0.0, 0.0, 4.0]) if params.rest_check > 0.5 else 0.0)
        ref = bb.run(gyro, acc, seq.mag if use_mag else None, dt, params, q0=q0, acc_trust=trusts[0],
                     mag_trust=trusts[1], bias_trust=trusts[2])
        s = bb.start_state(params, q0)
        q, f = np.zeros((n, 4)), np.zeros((n, 6))
        args = [np.ascontiguousarray(v, dtype=np.float64) for v in
                (np.asarray(params.vector()), s, gyro, acc, seq.mag, dt, *trusts)]
        lib.bb_run(*[a.ctypes.data_as(dbl) for a in args], ct.c_int(n), ct.c_int(int(use_mag)),
                   q.ctypes.data_as(dbl), f.ctypes.data_as(dbl))
        assert np.abs(q - ref["quat"]).max() < 1e-9
        assert np.abs(f[:, 0:3] - ref["gyro_bias"]).max() < 1e-11
        assert np.array_equal(f[:, 3] > 0.5, ref["rest"])
        assert np.array_equal(f[:, 4] > 0.5, ref["mag_disturbed"])
        if params.rest_bias > 0.5:
            assert ref["rest"].any()
        if use_mag and params.mag_rejection > 0.5:
            assert ref["mag_disturbed"].any()
        if params.rest_check > 0.5:   # the check took the rest's bias (beyond VQF's 2 °/s clip)
            assert np.abs(np.degrees(ref["gyro_bias"][-1, 2]) - 4.0) < 0.5


@needs_cc
@pytest.mark.parametrize("axes", [9, 6])
def test_untrained_model_runs_as_the_backbone(tmp_path, axes):
    """The untrained residual model (= the backbone) generated as C: BackboneStreaming's numbers."""
    pytest.importorskip("numba")
    from test_residual import residual_model

    from tcn_ahrs.streaming import BackboneStreaming

    model = residual_model(axes).eval()
    gen = generate_c(model, "untrained")
    (tmp_path / "untrained.h").write_text(gen["h"])
    (tmp_path / "untrained.c").write_text(gen["c"])
    c_rt = CRuntime(compile_c(tmp_path / "untrained.c", tmp_path / "lib.so", "double", CC), "untrained", axes)
    seq = simulate("drone", 30.0, 100.0, seed=2, axes=axes)
    ang, dw = _compare(c_rt, BackboneStreaming(model), _imu(seq, axes), np.float32(0.01), seq.quat[0])
    assert ang < 1e-6 and dw < 1e-6


# ------------------------------------------------------------------ shipped checkpoints
@pytest.mark.parametrize("real", ["double", "float"])
@pytest.mark.parametrize("name", NAMES)
def test_shipped_checkpoint_matches_the_streaming_runtime_on_a_simulated_recording(runtimes, name, real):
    c_rt, stream = runtimes[name, real]
    axes = _axes(name)
    for profile, seed in (("walking", 1), ("fast_rotation", 2), ("drone", 3)):
        seq = simulate(profile, 60.0, 200.0, seed=seed, axes=axes)
        ang, dw = _compare(c_rt, stream, _imu(seq, axes), np.float32(1.0 / 200.0), seq.quat[0])
        assert ang <= TOL, (profile, ang)
        assert dw < 1e-5


@pytest.mark.parametrize("real", ["double", "float"])
@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("rec", ["05_undisturbed_slow_rotation_with_breaks_B", "29_disturbed_stationary_magnet_B"])
def test_shipped_checkpoint_matches_the_streaming_runtime_on_broad(runtimes, name, rec, real):
    from tcn_ahrs.datasets import broad

    if not (BROAD / f"{rec}.hdf5").is_file():
        pytest.skip(f"BROAD recording {rec} not found under ../shared/datasets/broad")
    c_rt, stream = runtimes[name, real]
    axes = _axes(name)
    seq = broad.load_recording(BROAD, rec)
    k0 = int(np.argmax(np.isfinite(seq.quat).all(1)))
    ang, dw = _compare(c_rt, stream, _imu(seq, axes), np.float32(1.0 / seq.rate), seq.quat[k0])
    assert ang <= TOL, ang
    assert dw < 1e-5


@needs_cc
@pytest.mark.parametrize("flags", [[], ["-march=native"]])
def test_vector_loops_equal_the_scalar_loops(built, tmp_path, flags):
    """The networks' vector sums (GNU C vectors: SSE, NEON; the AVX2 copy chosen at run time;
    AVX with -march=native) add each output in the scalar loop's order, a multiply then an add
    per lane: the same floats out as -DTCN_AHRS_NO_DISPATCH's (portable vectors only),
    -DTCN_AHRS_NO_VECTOR's (scalar loops) and -DTCN_AHRS_BLOCK=1's (one sample per pass) builds."""
    c_vec, _, paths = built["oxiod9"]
    if flags:
        c_vec = CRuntime(compile_c(paths["c"], tmp_path / "libv.so", "double", CC, flags), "oxiod9", 9)
    others = [CRuntime(compile_c(paths["c"], tmp_path / f"lib{i}.so", "double", CC, [f, *flags]), "oxiod9", 9)
              for i, f in enumerate(["-DTCN_AHRS_NO_VECTOR", "-DTCN_AHRS_NO_DISPATCH", "-DTCN_AHRS_BLOCK=1"])]
    imu = _imu(simulate("walking", 20.0, 200.0, seed=3, axes=9), 9)
    outs = []
    for rt in (c_vec, *others):
        rt.reset(np.array([1.0, 0.0, 0.0, 0.0], np.float32))
        code, out = rt.run(imu, np.float32(0.005))
        assert code == 0
        outs.append(out)
    assert all(np.array_equal(outs[0], o) for o in outs[1:])


@needs_cc
@pytest.mark.parametrize("name", ["oxiod9", "tumvi6"])
def test_run_in_blocks_equals_one_step_at_a_time(runtimes, name):
    """name_run passes the networks over BLOCK samples at a time (each weight read once per
    block); every output and the state after it are the floats of name_step called per sample,
    whatever the block boundaries (lengths not a multiple of the block, runs split anywhere)."""
    from tcn_ahrs.export.c.runtime import BLOCK

    c_rt, _ = runtimes[name, "float"]
    axes = _axes(name)
    imu = _imu(simulate("walking", 4.0, 200.0, seed=7, axes=axes), axes)
    n, q0 = 3 * BLOCK * 20 + 5, np.array([1.0, 0.0, 0.0, 0.0], np.float32)
    c_rt.reset(q0)
    steps = np.array([np.concatenate(c_rt.step(x, 0.005)[1:3]) for x in imu[:n]])
    after_steps = c_rt.snapshot()
    c_rt.reset(q0)
    parts = [c_rt.run(imu[a:b], 0.005) for a, b in ((0, 3), (3, BLOCK + 4), (BLOCK + 4, n))]
    assert all(code == 0 for code, _ in parts)
    assert np.array_equal(np.concatenate([o for _, o in parts]), steps)
    assert c_rt.snapshot() == after_steps


@needs_cc
def test_float_build_keeps_the_filters_in_double(built, runtimes):
    """The float build's state: the backbone's arrays (its low-pass states among them) stay
    double, so it differs from the double build only in q0, m_conj and last_dt."""
    c_dbl, _, paths = built["oxiod9"]
    c_flt, _ = runtimes["oxiod9", "float"]
    assert 0 < c_dbl.state_size - c_flt.state_size <= 9 * 4
    assert "double s[OXIOD9_N_STATE]" in Path(paths["h"]).read_text()
    src = Path(paths["c"]).read_text()
    assert "static WREAL oxiod9_bb_lp(" in src
    assert "static void oxiod9_bb_gyro_update(WREAL *s, const WREAL *p, const WREAL *c, REAL gx" in src


def test_networks_that_are_off_are_not_in_the_runtime(built):
    """Under its knobs broad9 applies neither network (gyro_clip 0, trust_weight 0): its C
    runtime is the backbone alone (no weights, no ring buffers; its parity is tested above);
    tumvi6 keeps the trust net only (half the ring buffers of oxiod9/euroc6's two nets)."""
    from tcn_ahrs.checkpoint import model_from_checkpoint
    from tcn_ahrs.export.c.runtime import live_networks

    live = {n: live_networks(model_from_checkpoint(PATHS[n])) for n in ("broad9", "tumvi6", "euroc6")}
    assert live == {"broad9": (), "tumvi6": ("trust",), "euroc6": ("gyro", "trust")}
    size = {n: built[n][0].state_size for n in ("broad9", "tumvi6", "euroc6")}
    assert size["broad9"] < 2048
    assert 0.45 < (size["tumvi6"] - size["broad9"]) / (size["euroc6"] - size["broad9"]) < 0.55
    assert "conv(st" not in Path(built["broad9"][2]["c"]).read_text()


# ------------------------------------------------------------------ bad inputs
@pytest.mark.parametrize("name", ["broad9", "oxiod9", "euroc6"])
def test_bad_samples_are_refused_before_the_state_changes(built, name):
    c_rt, _, _ = built[name]
    axes = _axes(name)
    seq = simulate("walking", 3.0, 200.0, seed=4, axes=axes)
    imu = _imu(seq, axes)
    dt = 1.0 / 200.0
    q0 = seq.quat[0]
    c_rt.reset(q0)
    _, ref = c_rt.run(imu, dt)
    k = 300
    cases = []
    for ch, v, code in ((4, np.nan, 1), (0, np.inf, 1), (axes - 1, -np.inf, 1), (1, 1e3, 2), (5, -1e5, 2)):
        bad = imu[k].copy()
        bad[ch] = v
        cases.append((bad, dt, code))
    cases += [(imu[k], 0.0, 3), (imu[k], -dt, 3), (imu[k], np.nan, 3), (imu[k], np.inf, 3), (imu[k], 2.0, 3)]
    # the fault trial's tiny steps (one left the bias NaN for good): below conventions.MIN_DT
    cases += [(imu[k], d, 3) for d in (1e-14, 1e-9, 0.5 * MIN_DT)]
    c_rt.reset(q0)
    c_rt.run(imu[:k], dt)
    for bad, d, want in cases:
        before = c_rt.snapshot()
        code, *_ = c_rt.step(bad, d)
        assert code == want
        assert c_rt.snapshot() == before  # no state changed
    code, out = c_rt.run(imu[k:], dt)  # as if the bad samples had never come
    assert code == 0
    assert np.array_equal(out, ref[k:])
    # the first sample after reset refused: the start waits for the first good one
    c_rt.reset(q0)
    assert c_rt.step(cases[0][0], dt)[0] == 1
    assert np.array_equal(c_rt.run(imu[:10], dt)[1], ref[:10])
    # run() stops at the first refused sample with its code (here inside a block of the
    # networks' pass): the samples before it as run alone, the state as after them
    c_rt.reset(q0)
    bad = imu[:20].copy()
    bad[11, 2] = np.nan
    code, out = c_rt.run(bad, dt)
    assert code == 1 and np.array_equal(out[:11], ref[:11])
    after_bad = c_rt.snapshot()
    c_rt.reset(q0)
    c_rt.run(imu[:11], dt)
    assert c_rt.snapshot() == after_bad
    assert c_rt.reset([0.0, 0.0, 0.0, 0.0]) == 4
    assert c_rt.reset([np.nan, 0.0, 0.0, 1.0]) == 4


@needs_cc
def test_flags_report_rest_and_magnetic_disturbance(built):
    c_rt, _, _ = built["broad9"]
    seq = simulate("static", 10.0, 100.0, seed=1, axes=9)
    imu = _imu(seq, 9)
    c_rt.reset(seq.quat[0])
    flags = [c_rt.step(imu[k], 0.01)[4] for k in range(imu.shape[0])]
    assert flags[-1] & 1  # rest detected once still long enough
    assert flags[0] & 2   # the field is unknown (disturbed) until accepted
    code, _, _, bias, fl = c_rt.step(np.r_[imu[-1, :6], 0.0, 0.0, 0.0], 0.01)
    assert code == 0 and fl & 8 and np.isfinite(bias).all()


# ------------------------------------------------------------------ refusals
@pytest.mark.parametrize("ckpt", ["closed_loop/broad9.ckpt", "paper/broad6_open_loop.ckpt"])
def test_non_residual_checkpoints_are_refused(tmp_path, ckpt):
    with pytest.raises(ExportError, match="residual"):
        export_c(CKPTS / ckpt, tmp_path, "x")
    assert not list(tmp_path.iterdir())


def test_name_must_be_a_c_identifier(tmp_path):
    with pytest.raises(ExportError, match="identifier"):
        export_c(CKPTS / "broad6_residual.ckpt", tmp_path, "9-lives")


# ------------------------------------------------------------------ the example
@needs_cc
def test_csv_example_builds_and_streams(built, tmp_path):
    c_rt, _, paths = built["broad9"]
    for k in ("h", "c"):
        shutil.copy(paths[k], tmp_path)
    exe = tmp_path / "stream"
    cmd = [CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-DMODEL=broad9", '-DMODEL_HEADER="broad9.h"',
           str(ROOT / "examples" / "c" / "stream.c"), str(tmp_path / "broad9.c"), "-I", str(tmp_path), "-o", str(exe),
           "-lm"]
    build = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr[-2000:]
    seq = simulate("walking", 5.0, 100.0, seed=3, axes=9)
    imu = _imu(seq, 9)
    imu[50, 1] = np.nan  # refused, reported, and the stream goes on
    np.savetxt(tmp_path / "imu.csv", imu, delimiter=",", fmt="%.9g", header="gx,gy,gz,ax,ay,az,mx,my,mz")
    q0 = [repr(float(v)) for v in seq.quat[0]]
    run = subprocess.run([str(exe), str(tmp_path / "imu.csv"), "0.01", *q0], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "median step time" in run.stderr and "1 refused" in run.stderr
    lines = run.stdout.strip().splitlines()
    assert len(lines) == imu.shape[0] and lines[50] == "refused,1"
    got = np.array([[float(v) for v in ln.split(",")] for i, ln in enumerate(lines) if i != 50])
    c_rt.reset(seq.quat[0])
    ref = np.stack([c_rt.step(imu[k], 0.01)[1] for k in range(imu.shape[0]) if k != 50])
    assert np.abs(got[:, :4] - ref).max() < 1e-6


# ------------------------------------------------------------------ the translator's subset
TOY = '''
import math
from tcn_ahrs.kernels.ops import float_ops
ops = float_ops()
jit, where = ops.jit, ops.where
N_OFF = 2
HALF = 0.5

@jit
def swap(s, x, y):
    x, y = y, x * HALF           # Python evaluates the right-hand side first
    return x, y

@jit
def step(s, p, x):
    a, b = swap(s, x, s[N_OFF])
    for i in range(3):
        s[i] = where(s[i] > a, s[i] - b, s[i] + a / 7)
    if p[0] > 0.5:
        s[N_OFF + 1] = math.sqrt(a * a + b ** 2) + 3 / 4
'''


def _toy(tmp_path, text, name):
    import importlib.util

    f = tmp_path / f"{name}.py"
    f.write_text(text)
    spec = importlib.util.spec_from_file_location(name, f)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@needs_cc
@pytest.mark.parametrize("wide", [(), ("swap",), ("step",)])
def test_translator_keeps_python_semantics(tmp_path, wide):
    """The toy kernel in C equals Python's, with either function computed in WREAL (the
    conversions between the two scalar types are explicit: the float build compiles with
    -Wdouble-promotion -Werror)."""
    import ctypes as ct

    mod = _toy(tmp_path, TOY, "toy_kernel")
    src, sig = kernel_c(mod, "toy_", ["step"], wide)
    assert "const WREAL *p" in sig["step"]
    assert ("WREAL *ret1" if "swap" in wide else "REAL *ret1") in sig["swap"]
    (tmp_path / "toy.c").write_text("#include <math.h>\n" + template("helpers.h.in") + src.replace("static void toy_step", "void toy_step"))
    compile_c(tmp_path / "toy.c", tmp_path / "libtoy_f.so", "float", CC)
    lib = ct.CDLL(compile_c(tmp_path / "toy.c", tmp_path / "libtoy.so", "double", CC))
    dbl = ct.POINTER(ct.c_double)
    for flag in (0.0, 1.0):
        s_py = np.array([0.3, -2.0, 1.5, 9.0])
        s_c = s_py.copy()
        p = np.array([flag])
        mod.step(s_py, p, 0.7)
        lib.toy_step(s_c.ctypes.data_as(dbl), p.ctypes.data_as(dbl), ct.c_double(0.7))
        assert np.array_equal(s_c, s_py)
        assert (s_py[3] != 9.0) == bool(flag)


@pytest.mark.parametrize("body", ["    while x > 0:\n        x = x - 1\n", "    s[0] = x % 2\n",
                                  "    s[0] = [x][0]\n", "    s[0] = x ** 3\n"])
def test_translator_refuses_what_is_outside_the_subset(tmp_path, body):
    text = "from tcn_ahrs.kernels.ops import float_ops\njit = float_ops().jit\n\n@jit\ndef k(s, x):\n" + body
    mod = _toy(tmp_path, text, "bad_kernel")
    with pytest.raises(ExportError, match="outside the kernel subset"):
        kernel_c(mod, "b_", ["k"])


def test_export_command_writes_the_c_files_and_keeps_earlier_ones(tmp_path, capsys):
    """``tcn-ahrs export format=c out=DIR/NAME.c``: NAME.c + NAME.h; existing files are refused
    unless overwrite=true (nothing the user produced is overwritten); out must name the .c file."""
    from tcn_ahrs.cli import main

    out = tmp_path / "broad9.c"
    main(["export", f"ckpt={CKPTS / 'broad9_residual.ckpt'}", "format=c", f"out={out}"])
    assert out.is_file() and (tmp_path / "broad9.h").is_file()
    assert "broad9_step" in (tmp_path / "broad9.h").read_text()
    before = out.read_text()
    out.write_text("/* mine */")
    with pytest.raises(SystemExit) as e:
        main(["export", f"ckpt={CKPTS / 'broad9_residual.ckpt'}", "format=c", f"out={out}"])
    assert e.value.code == 2 and "already exist" in capsys.readouterr().err
    assert out.read_text() == "/* mine */"
    main(["export", f"ckpt={CKPTS / 'broad9_residual.ckpt'}", "format=c", f"out={out}", "overwrite=true"])
    assert out.read_text() == before
    assert not list(tmp_path.glob(".*.partial"))
    with pytest.raises(SystemExit) as e:
        main(["export", f"ckpt={CKPTS / 'broad9_residual.ckpt'}", "format=c", f"out={tmp_path / 'model.pt'}"])
    assert e.value.code == 2 and "must name the C file" in capsys.readouterr().err


# ------------------------------------------------------------------ a tuned classical filter
def _ecf_file(tmp_path, axes, calibrated):
    """An ECF file as tcn-ahrs search writes it: tuned knobs and, ``calibrated``, a static
    calibration with biases, scale and misalignment in every sensor."""
    from tcn_ahrs.calibration import StaticCalibration
    from tcn_ahrs.estimators.families import save_estimator

    cal = None
    if calibrated:
        rot = np.array([[1.0, -0.02, 0.01], [0.02, 1.0, -0.015], [-0.01, 0.015, 1.0]])
        cal = StaticCalibration(gyro_matrix=1.03 * rot, gyro_bias=np.array([0.02, -0.01, 0.03]),
                                acc_matrix=0.98 * rot.T, acc_bias=np.array([0.1, -0.05, 0.2]),
                                mag_matrix=1.1 * rot, hard_iron=np.array([5.0, -3.0, 8.0]))
    path = tmp_path / f"ecf{axes}{'_cal' if calibrated else ''}.json"
    save_estimator(path, "ecf", axes, {"k_norm": 0.3, "a_min": 1.5}, cal)
    return path


@needs_cc
@pytest.mark.parametrize("axes", [6, 9])
@pytest.mark.parametrize("calibrated", [False, True])
def test_tuned_ecf_exports_as_its_c_kernel(tmp_path, axes, calibrated):
    """A tuned ECF file (the classical family tcn-ahrs search ships for TUM VI and OxIOD) exports
    to C: Eqs. 5-8 and Eq. 4 translated from kernels/classical.py, its knobs and calibration
    written in; over a simulated minute both builds equal the estimator tcn-ahrs evaluate runs
    (float ≤ 1e-4 rad, double ≤ 1e-6 rad: its float32 outputs) and refuse bad samples unchanged."""
    import dataclasses

    from tcn_ahrs.estimators.families import load_estimator

    path = _ecf_file(tmp_path, axes, calibrated)
    paths = export_c(path, tmp_path, "ecf")
    seq = simulate("walking", 60.0, 200.0, seed=3, axes=axes)
    imu = _imu(seq, axes)
    as_read = dataclasses.replace(seq, gyro=imu[:, :3].astype(np.float64), accel=imu[:, 3:6].astype(np.float64),
                                  mag=imu[:, 6:].astype(np.float64) if axes == 9 else None, check_units=False)
    est = load_estimator(path)
    est.inner = est.inner.with_params(heading_ref="init")  # the runtime's: the field of its first sample
    q0 = seq.quat[0].astype(np.float32)
    ref = est.run(as_read, init_quat=q0.astype(np.float64)).quat
    for real, bound in (("float", 1e-4), ("double", 1e-6)):
        rt = CRuntime(compile_c(paths["c"], tmp_path / f"libecf_{real}.so", real, CC), "ecf", axes)
        rt.reset(q0)
        code, out = rt.run(imu, np.float32(0.005))
        assert code == 0
        assert _angle(out[:, :4].astype(np.float64), np.asarray(ref)).max() < bound, real
    before = rt.snapshot()
    bad = imu[10].copy()
    bad[2] = np.nan
    assert rt.step(bad, 0.005)[0] == 1 and rt.snapshot() == before


def test_classical_families_without_a_c_kernel_are_named(tmp_path):
    from tcn_ahrs.estimators.families import save_estimator

    save_estimator(tmp_path / "m.json", "mahony", 6, {}, None)
    with pytest.raises(ExportError, match=r"family 'mahony'; format=c holds the residual models and the classical "
                                          r"families \['ecf'\]"):
        export_c(tmp_path / "m.json", tmp_path, "m")
