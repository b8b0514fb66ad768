"""ONNX Runtime vs TorchScript for the streaming networks' per-sample step (the shipped broad9).

The networks' step alone (the three calibration TCNs stacked, ring buffers as explicit inputs
and outputs, the calibration head), exported with torch.onnx's TorchScript-based exporter and
run by onnxruntime on 1 thread, beside the same functional module in TorchScript. Needs
``pip install onnx onnxscript`` (not project dependencies). Run from the repository root:

    python docs/results/onnx_streaming_probe.py

2026-12-02, 2-core AMD EPYC, idle: onnxruntime 54.5 us, TorchScript 65.5 us per sample (the
whole CompiledStreaming step, networks and filter, 16 us in the speed benchmark).
"""
import time, statistics, warnings, math
import numpy as np, torch
warnings.simplefilter("ignore")
torch.set_num_threads(1)
from torch import nn, Tensor
from tcn_ahrs.checkpoint import model_from_checkpoint
from tcn_ahrs.export import ClosedLoopStreaming
from tcn_ahrs.bench.common import synthetic_imu

m = model_from_checkpoint("checkpoints/broad9_residual.ckpt").eval()
ts = ClosedLoopStreaming(m, {"rate_hz": 285.7})
K = ts.kernel_size

class NetStep(nn.Module):
    def __init__(self, ts):
        super().__init__()
        self.g = ts.groups
        self.register_buffer("w0", ts.first_weight_t.clone()); self.register_buffer("b0", ts.first_bias_step.clone())
        self.ws = nn.ParameterList([nn.Parameter(w.clone(), requires_grad=False) for w in ts.step_weights])
        self.bs = nn.ParameterList([nn.Parameter(b.clone(), requires_grad=False) for b in ts.step_biases])
        self.register_buffer("hw", ts.head_weight.float().clone()); self.register_buffer("hb", ts.head_bias.float().clone())
        self.register_buffer("hm", ts.head_matrix.float().clone())
    def forward(self, x, r0, r1, r2, r3, t0, t1, t2, t3, p0, p1, p2, p3):
        r0 = r0.index_copy(0, p0, x.view(1, -1))
        u = torch.addmm(self.b0, r0.index_select(0, t0).view(1, -1), self.w0)
        h = (u + u * torch.erf(u)).view(self.g, 1, -1)
        rings = []
        for r, t, p, w, b in ((r1, t1, p1, self.ws[0], self.bs[0]), (r2, t2, p2, self.ws[1], self.bs[1]), (r3, t3, p3, self.ws[2], self.bs[2])):
            r = r.index_copy(1, p, h)
            u = torch.baddbmm(b, r.index_select(1, t).view(self.g, 1, -1), w)
            h = u + u * torch.erf(u)
            rings.append(r)
        head = self.hm @ x - (self.hw @ h.reshape(-1) + self.hb)
        return head, r0, rings[0], rings[1], rings[2]

net = NetStep(ts).eval()
spans = [ts.first_span] + list(ts.spans)
dil = [ts.first_dilation] + list(ts.hidden_dilations)
rings = [torch.zeros(spans[0], 9)] + [torch.zeros(ts.groups, s, b.shape[1] // K) for s, b in zip(spans[1:], ts.step_weights)]
def idx(t):
    taps = [torch.tensor([(t - (K - 1 - j) * d) % s for j in range(K)]) for s, d in zip(spans, dil)]
    pos = [torch.tensor([t % s]) for s in spans]
    return taps, pos
x = synthetic_imu(1, 2000, 9, 100.0, 0)["imu"][0]
taps, pos = idx(5)
args = (x[0], *rings, *taps, *pos)
torch.onnx.export(net, args, "/tmp/probe/netstep.onnx", dynamo=False, input_names=["x","r0","r1","r2","r3","t0","t1","t2","t3","p0","p1","p2","p3"])
import onnxruntime as ort
so = ort.SessionOptions(); so.intra_op_num_threads = 1; so.inter_op_num_threads = 1
sess = ort.InferenceSession("/tmp/probe/netstep.onnx", so, providers=["CPUExecutionProvider"])
names = [i.name for i in sess.get_inputs()]
# precomputed index arrays per phase (not timed): the caller's bookkeeping
R = [r.numpy() for r in rings]
xs = x.numpy()
ref = net(*args)[0]
feed = dict(zip(names, [xs[0]] + R + [t.numpy() for t in taps] + [p.numpy() for p in pos]))
out = sess.run(None, feed)
print("onnx vs torch head max diff", float(np.abs(out[0] - ref.numpy()).max()))
pre = [idx(t) for t in range(2000)]
pre_np = [([t.numpy() for t in a], [p.numpy() for p in b]) for a, b in pre]
def run_ort(n):
    global R
    ts_ = []
    for t in range(n):
        a, b = pre_np[t]
        f = {"x": xs[t], "r0": R[0], "r1": R[1], "r2": R[2], "r3": R[3], "t0": a[0], "t1": a[1], "t2": a[2], "t3": a[3],
             "p0": b[0], "p1": b[1], "p2": b[2], "p3": b[3]}
        t0 = time.perf_counter_ns()
        o = sess.run(None, f)
        ts_.append(time.perf_counter_ns() - t0)
        R = o[1:]
    return statistics.median(ts_[200:]) / 1e3
scripted = torch.jit.freeze(torch.jit.script(net))
def run_ts(n):
    rr = rings
    ts_ = []
    for t in range(n):
        a, b = pre[t]
        t0 = time.perf_counter_ns()
        o = scripted(x[t], *rr, *a, *b)
        ts_.append(time.perf_counter_ns() - t0)
        rr = list(o[1:])
    return statistics.median(ts_[200:]) / 1e3
with torch.no_grad():
    for rep in range(2):
        print("networks' step, median us: onnxruntime %.1f, TorchScript (same functional module) %.1f" % (run_ort(2000), run_ts(2000)))
