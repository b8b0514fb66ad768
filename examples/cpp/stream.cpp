// Streams IMU samples through an exported tcn-ahrs streaming module from C++ (libtorch only,
// no Python): reset(q0), then step(sample, dt) per sample.
//
//   stream MODEL_streaming.pt IMU.csv DT [OUT.csv]
//
// IMU.csv: one sample per line, C comma-separated raw readings (gyro rad/s, acc m/s^2, mag uT
// for 9-axis models; the body frame; see the module's metadata()). DT: seconds between
// samples. Writes one line per sample, "qw,qx,qy,qz,wx,wy,wz" (nav_from_body, ENU; the applied
// rate in rad/s), to OUT.csv (default: stdout), and the median / p99 latency of step() on one
// thread to stderr. The initial attitude is the identity (a real caller passes its own q0).
#include <ATen/Parallel.h>
#include <torch/script.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

int main(int argc, char** argv) {
  if (argc < 4) {
    std::cerr << "usage: stream MODEL_streaming.pt IMU.csv DT [OUT.csv]" << std::endl;
    return 2;
  }
  at::set_num_threads(1);
  torch::NoGradGuard no_grad;
  torch::jit::Module m = torch::jit::load(argv[1]);
  const double dt = std::stod(argv[3]);

  std::vector<std::vector<float>> rows;
  std::ifstream in(argv[2]);
  if (!in) {
    std::cerr << argv[2] << ": cannot open" << std::endl;
    return 2;
  }
  for (std::string line; std::getline(in, line);) {
    if (line.empty()) continue;
    std::vector<float> r;
    std::stringstream ss(line);
    for (std::string cell; std::getline(ss, cell, ',');) r.push_back(std::stof(cell));
    rows.push_back(r);
  }
  std::FILE* out = argc > 4 ? std::fopen(argv[4], "w") : stdout;
  if (!out) {
    std::cerr << argv[4] << ": cannot write" << std::endl;
    return 2;
  }
  m.get_method("reset")({torch::tensor({1.0, 0.0, 0.0, 0.0}, torch::kFloat64)});
  torch::jit::Method step = m.get_method("step");
  std::vector<double> us;
  for (const auto& r : rows) {
    at::Tensor sample = torch::from_blob(const_cast<float*>(r.data()), {static_cast<long>(r.size())},
                                         torch::kFloat32).clone();
    auto t0 = std::chrono::steady_clock::now();
    auto res = step({sample, dt}).toTuple();  // errors (bad shape, NaN, dt <= 0) raise here
    auto t1 = std::chrono::steady_clock::now();
    us.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
    at::Tensor q = res->elements()[0].toTensor(), w = res->elements()[1].toTensor();
    const double* qp = q.data_ptr<double>();
    const double* wp = w.data_ptr<double>();
    std::fprintf(out, "%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g\n", qp[0], qp[1], qp[2], qp[3], wp[0], wp[1], wp[2]);
  }
  if (out != stdout) std::fclose(out);
  std::sort(us.begin(), us.end());
  if (!us.empty())
    std::cerr << "step latency, 1 thread: median " << us[us.size() / 2] << " us, p99 " << us[us.size() * 99 / 100]
              << " us over " << us.size() << " samples" << std::endl;
  return 0;
}
