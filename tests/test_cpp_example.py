"""The C++ example (examples/cpp/stream.cpp) runs an exported streaming module with libtorch
alone and gives the numbers the module gives in Python, sample by sample."""

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from tcn_ahrs.export import export_streaming

from test_export_closed_loop import N, RATE, _imu, _model  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_cpp_example_streams_like_python(tmp_path):
    from torch.utils import cpp_extension

    cxx = shutil.which("g++") or shutil.which("c++")
    inc = [Path(p) for p in cpp_extension.include_paths()]
    if cxx is None or not (inc[0] / "torch" / "script.h").is_file():
        pytest.skip("no C++ compiler or no libtorch headers in this torch install")
    exe = tmp_path / "stream"
    libs = cpp_extension.library_paths()
    abi = int(torch._C._GLIBCXX_USE_CXX11_ABI)
    cmd = ([cxx, "-O1", "-std=c++17", str(ROOT / "examples" / "cpp" / "stream.cpp"), "-o", str(exe),
            f"-D_GLIBCXX_USE_CXX11_ABI={abi}"] + [f"-I{p}" for p in inc] + [f"-L{p}" for p in libs]
           + [f"-Wl,-rpath,{p}" for p in libs] + ["-ltorch", "-ltorch_cpu", "-lc10"])
    build = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr[-2000:]

    export_streaming(_model(9), tmp_path / "s.pt", {"rate_hz": RATE})
    imu = _imu(9, 1).numpy().astype(np.float32)
    np.savetxt(tmp_path / "imu.csv", imu, delimiter=",", fmt="%.9g")  # float32 round-trips exactly
    run = subprocess.run([str(exe), str(tmp_path / "s.pt"), str(tmp_path / "imu.csv"), repr(1.0 / RATE),
                          str(tmp_path / "out.csv")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "median" in run.stderr
    got = np.loadtxt(tmp_path / "out.csv", delimiter=",")

    m = torch.jit.load(str(tmp_path / "s.pt"))
    m.reset(torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    ref = np.stack([torch.cat(m.step(torch.from_numpy(imu[k]), 1.0 / RATE)).numpy() for k in range(N)])
    assert got.shape == (N, 7)
    assert np.abs(got - ref).max() < 1e-12
