// The calibration benchmark, Ceres side: calib-core's LS problem solved with Ceres Solver.
//
// Reads the datasets that `calib-core/examples/export_dataset.rs` writes (DIR/samples.csv,
// DIR/tables.csv; the format is documented there and read by benches/scipy_ls.py too) and
// solves, from Table 1, for all 28 D-H parameters, minimising the same sum of squared pose
// errors as calib-core's `identify_ls`:
//
// * the same model: standard D-H, T_i = Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i), the 28
//   parameters in calib-core's order (a1..a7, d1..d7, alpha1..alpha7, theta1..theta7), one
//   parameter block;
// * the same residual: calib-core's tool-frame pose error (calib-core/src/model.rs,
//   `pose_error`), e = [R_m^T (p_a - p_m); log(R_m^T R_a)], one residual block of 6 rows per
//   sample (Ceres minimises 1/2 sum |e|^2, the same optimum);
// * variants:
//   - `analytic`: a SizedCostFunction<6, 28> with calib-core's analytic Jacobian -M(e) J
//     (`fk_jacobian` and `error_jacobian`, ported operation for operation), the twists' sin and
//     cos computed once per evaluation point (an EvaluationCallback marks a new point; the
//     first residual block evaluated there refreshes them), not once per sample;
//   - `autodiff`: an AutoDiffCostFunction<6, 28> of the same residual written once over a
//     scalar type (Ceres' Jets, 28 dual parts);
//   both with DENSE_NORMAL_CHOLESKY (Ceres forms J^T J of the dense 6K x 28 Jacobian with
//   Eigen and factors it), Jacobi column scaling (Ceres' default, calib-core's counterpart),
//   Levenberg-Marquardt, one thread.
//
// Tolerances: Ceres stops when the relative cost change of a step falls below
// `function_tolerance`, the step below `parameter_tolerance` (relative to |x|), or the
// gradient's max-norm below `gradient_tolerance`, and then keeps the point before that step.
// The defaults here (--ftol 1e-12 --ptol 1e-12 --gtol 1e-14) stop it at calib-core's optimum:
// the cost within 1e-12 (relative) of calib-core's (the bench and xtask's test check it).
//
// Every variant runs --repeats times on every dataset; one run is building the
// ceres::Problem (one residual block per sample) and Solve, timed with the process CPU clock
// (CLOCK_PROCESS_CPUTIME_ID, as calib-core's and scipy's sides are, so that other processes on
// a shared core do not count) and the wall clock; Solve alone is timed too. Reading the CSV
// is not timed. One JSON object per line goes to stdout:
//   {"bench":"ceres-check", "k", "ceres", "eigen", "cost_start", "jac_max_abs_diff", ...}
//   {"bench":"ceres", "variant", "k", "median_s", "runs_s", "wall_median_s", "solve_median_s",
//    "iterations", "jacobian_evaluations", "residual_evaluations", "termination", "cost", "y",
//    "err_a", "err_d", "err_alpha", "err_theta", "err_norm", "jacobian_evaluation_s",
//    "residual_evaluation_s", "linear_solver_s", "minimizer_s" (Ceres' own wall-clock split of
//    the last run), "x": [28 values]}
//
// Usage: ceres_ls DIR... [--repeats 5] [--variants analytic,autodiff] [--ftol F] [--ptol F]
//        [--gtol F] [--verbose]
// Built by `cargo xtask bench --only calib` (xtask/src/bench/ceres.rs has the g++ command).

#include <ceres/ceres.h>
#include <ceres/version.h>
#include <time.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

namespace {

constexpr int N = 7;
constexpr int P = 4 * N;
constexpr int kA = 0, kD = N, kAlpha = 2 * N, kTheta = 3 * N;

// ---------------------------------------------------------------------------------------------
// Data

struct Dataset {
  std::string dir;
  int k = 0;
  std::vector<std::array<double, N>> q;
  std::vector<std::array<double, 9>> ra;  // row-major
  std::vector<std::array<double, 3>> pa;
  std::array<double, P> start{};
  std::array<double, P> truth{};
};

[[noreturn]] void die(const std::string& what) {
  std::fprintf(stderr, "ceres_ls: %s\n", what.c_str());
  std::exit(65);
}

std::vector<std::string> split(const std::string& line) {
  std::vector<std::string> out;
  std::stringstream ss(line);
  std::string field;
  while (std::getline(ss, field, ',')) out.push_back(field);
  return out;
}

double number(const std::string& s, const std::string& where) {
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s.c_str(), &end);
  if (end == s.c_str() || *end != '\0' || errno != 0 || !std::isfinite(v)) {
    die(where + ": `" + s + "` is not a finite number");
  }
  return v;
}

Dataset load(const std::string& dir) {
  Dataset d;
  d.dir = dir;
  std::ifstream samples(dir + "/samples.csv");
  if (!samples) die("cannot read " + dir + "/samples.csv");
  std::string line;
  std::getline(samples, line);  // header
  int row = 1;
  while (std::getline(samples, line)) {
    ++row;
    if (line.empty()) continue;
    const auto f = split(line);
    const std::string where = dir + "/samples.csv line " + std::to_string(row);
    if (f.size() != N + 12) die(where + ": expected 19 fields");
    std::array<double, N> q;
    std::array<double, 9> r;
    std::array<double, 3> p;
    for (int i = 0; i < N; ++i) q[i] = number(f[i], where);
    for (int i = 0; i < 9; ++i) r[i] = number(f[N + i], where);
    for (int i = 0; i < 3; ++i) p[i] = number(f[N + 9 + i], where);
    d.q.push_back(q);
    d.ra.push_back(r);
    d.pa.push_back(p);
  }
  d.k = static_cast<int>(d.q.size());
  if (d.k == 0) die(dir + "/samples.csv has no samples");
  std::ifstream tables(dir + "/tables.csv");
  if (!tables) die("cannot read " + dir + "/tables.csv");
  std::getline(tables, line);  // index,kind,joint,start,truth
  std::array<bool, P> seen{};
  row = 1;
  while (std::getline(tables, line)) {
    ++row;
    if (line.empty()) continue;
    const auto f = split(line);
    const std::string where = dir + "/tables.csv line " + std::to_string(row);
    if (f.size() != 5) die(where + ": expected 5 fields");
    const double index = number(f[0], where);
    if (index < 0 || index >= P || index != std::floor(index)) die(where + ": bad index");
    const int i = static_cast<int>(index);
    d.start[i] = number(f[3], where);
    d.truth[i] = number(f[4], where);
    seen[i] = true;
  }
  for (int i = 0; i < P; ++i) {
    if (!seen[i]) die(dir + "/tables.csv lacks parameter " + std::to_string(i));
  }
  return d;
}

// ---------------------------------------------------------------------------------------------
// The model, over any scalar T (double, or Ceres' Jet for autodiff). Rotations are row-major
// 3 x 3 arrays.

template <typename T>
struct Pose {
  T r[9];
  T p[3];
};

// T_i(q) * u for one link (calib-core's `DhRow::then`): the link transform composed with the
// pose u of the tool in the next frame, without forming T_i.
template <typename T>
void then(const T& a, const T& d, const T& theta, const T& sa, const T& ca, double q, const Pose<T>& u,
          Pose<T>* out) {
  using std::cos;
  using std::sin;
  const T angle = theta + q;
  const T st = sin(angle), ct = cos(angle);
  const T r0[3] = {ct, -st * ca, st * sa};
  const T r1[3] = {st, ct * ca, -ct * sa};
  for (int j = 0; j < 3; ++j) {
    out->r[0 * 3 + j] = r0[0] * u.r[0 * 3 + j] + r0[1] * u.r[1 * 3 + j] + r0[2] * u.r[2 * 3 + j];
    out->r[1 * 3 + j] = r1[0] * u.r[0 * 3 + j] + r1[1] * u.r[1 * 3 + j] + r1[2] * u.r[2 * 3 + j];
    out->r[2 * 3 + j] = sa * u.r[1 * 3 + j] + ca * u.r[2 * 3 + j];
  }
  out->p[0] = r0[0] * u.p[0] + r0[1] * u.p[1] + r0[2] * u.p[2] + a * ct;
  out->p[1] = r1[0] * u.p[0] + r1[1] * u.p[1] + r1[2] * u.p[2] + a * st;
  out->p[2] = (sa * u.p[1] + ca * u.p[2]) + d;
}

template <typename T>
void identity(Pose<T>* u) {
  for (int i = 0; i < 9; ++i) u->r[i] = T(0.0);
  u->r[0] = u->r[4] = u->r[8] = T(1.0);
  for (int i = 0; i < 3; ++i) u->p[i] = T(0.0);
}

// Rotation vector of a rotation matrix (calib-core's `log_so3`, away from pi: the pose errors
// here are far smaller; false near pi).
template <typename T>
bool log_so3(const T* r, T* w) {
  using std::atan2;
  using std::sqrt;
  const T v[3] = {T(0.5) * (r[7] - r[5]), T(0.5) * (r[2] - r[6]), T(0.5) * (r[3] - r[1])};
  const T s = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  const T c = T(0.5) * (r[0] + r[4] + r[8] - T(1.0));
  const T th = atan2(s, c);
  if (th < T(1e-3)) {
    const T f = T(1.0) + th * th / T(6.0);
    for (int i = 0; i < 3; ++i) w[i] = v[i] * f;
    return true;
  }
  if (th < T(M_PI - 1e-3)) {
    const T f = th / s;
    for (int i = 0; i < 3; ++i) w[i] = v[i] * f;
    return true;
  }
  return false;
}

// e = [R_m^T (p_a - p_m); log(R_m^T R_a)] (calib-core's `pose_error`).
template <typename T>
bool pose_error(const Pose<T>& m, const double* ra, const double* pa, T* e) {
  T dp[3];
  for (int i = 0; i < 3; ++i) dp[i] = pa[i] - m.p[i];
  for (int i = 0; i < 3; ++i) {
    e[i] = m.r[0 * 3 + i] * dp[0] + m.r[1 * 3 + i] * dp[1] + m.r[2 * 3 + i] * dp[2];
  }
  T rel[9];  // R_m^T R_a
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      rel[i * 3 + j] = m.r[0 * 3 + i] * ra[0 * 3 + j] + m.r[1 * 3 + i] * ra[1 * 3 + j] + m.r[2 * 3 + i] * ra[2 * 3 + j];
    }
  }
  return log_so3(rel, e + 3);
}

// The residual of sample s over any scalar type (the autodiff functor's body, and the cost).
template <typename T>
bool residual(const T* x, const Dataset& data, int s, T* e) {
  using std::cos;
  using std::sin;
  Pose<T> u, next;
  identity(&u);
  for (int i = N - 1; i >= 0; --i) {
    then(x[kA + i], x[kD + i], x[kTheta + i], sin(x[kAlpha + i]), cos(x[kAlpha + i]), data.q[s][i], u, &next);
    u = next;
  }
  return pose_error(u, data.ra[s].data(), data.pa[s].data(), e);
}

struct AutodiffResidual {
  const Dataset* data;
  int s;
  template <typename T>
  bool operator()(const T* x, T* e) const {
    return residual(x, *data, s, e);
  }
};

// ---------------------------------------------------------------------------------------------
// The analytic cost function

// sin and cos of the twists alpha, computed once per evaluation point: Ceres calls
// PrepareForEvaluation before it evaluates the residual blocks at a point, and the first block
// evaluated there refreshes them from its parameters (single-threaded: one thread evaluates).
class TwistTrig : public ceres::EvaluationCallback {
 public:
  void PrepareForEvaluation(bool, bool new_evaluation_point) override {
    if (new_evaluation_point) stale_ = true;
  }
  const double* sa_ca(const double* x) {
    if (stale_) {
      for (int i = 0; i < N; ++i) {
        sincos(x[kAlpha + i], &trig_[2 * i], &trig_[2 * i + 1]);
      }
      stale_ = false;
    }
    return trig_;
  }

 private:
  bool stale_ = true;
  double trig_[2 * N];
};

// One sample's residual and, when `jac` is not null, its Jacobian (row-major 6 x 28), with the
// twists' (sin, cos) given.
bool analytic_sample(const Dataset& data, int s, const double* x, const double* trig, double* e, double* jac) {
  const double* q = data.q[s].data();
  // Backward pass (calib-core's `fk_jacobian_into`): u is U_{i+1} = T_{i+1} ... T_N, the pose
  // of the tool in frame i; the columns are the tool-frame twists of unit parameter changes,
  // [v; w] per parameter.
  double cv[P][3], cw[P][3];  // w is zero for a and d
  Pose<double> u, next;
  identity(&u);
  for (int i = N - 1; i >= 0; --i) {
    const double sa = trig[2 * i], ca = trig[2 * i + 1];
    if (jac) {
      const double* r = u.r;
      const double* p = u.p;
      // U^T v for v = (0, v1, v2).
      auto rt_yz = [r](double v1, double v2, double* out) {
        out[0] = r[1 * 3 + 0] * v1 + r[2 * 3 + 0] * v2;
        out[1] = r[1 * 3 + 1] * v1 + r[2 * 3 + 1] * v2;
        out[2] = r[1 * 3 + 2] * v1 + r[2 * 3 + 2] * v2;
      };
      const double x_t[3] = {r[0], r[1], r[2]};
      double z_t[3], v_alpha[3];
      rt_yz(sa, ca, z_t);
      rt_yz(-p[2], p[1], v_alpha);
      const double a = x[kA + i];
      const double w[3] = {sa * p[2] - ca * p[1], ca * p[0] + a * ca, -(sa * p[0]) - a * sa};
      for (int j = 0; j < 3; ++j) {
        cv[kA + i][j] = x_t[j];
        cv[kD + i][j] = z_t[j];
        cv[kAlpha + i][j] = v_alpha[j];
        cw[kAlpha + i][j] = x_t[j];
        cv[kTheta + i][j] = r[0 * 3 + j] * w[0] + r[1 * 3 + j] * w[1] + r[2 * 3 + j] * w[2];
        cw[kTheta + i][j] = z_t[j];
      }
    }
    then(x[kA + i], x[kD + i], x[kTheta + i], sa, ca, q[i], u, &next);
    u = next;
  }
  if (!pose_error(u, data.ra[s].data(), data.pa[s].data(), e)) return false;
  if (!jac) return true;
  // The residual Jacobian -M(e) J (calib-core's `error_jacobian`): M = [I, -[e_p]x; 0, J_l^-1],
  // so a column [v; w] maps to [v + w x e_p; J_l^-1 w]; a and d columns have w = 0.
  const double ep[3] = {e[0], e[1], e[2]};
  const double er[3] = {e[3], e[4], e[5]};
  const double th = std::sqrt(er[0] * er[0] + er[1] * er[1] + er[2] * er[2]);
  double c;
  if (th < 1e-4) {
    c = 1.0 / 12.0 + th * th / 720.0;
  } else {
    double sn, cs;
    sincos(th, &sn, &cs);
    c = 1.0 / (th * th) - (1.0 + cs) / (2.0 * th * sn);
  }
  // J_l^-1 = I - K/2 + c K^2, K = [er]x.
  const double kk[9] = {0, -er[2], er[1], er[2], 0, -er[0], -er[1], er[0], 0};
  double jl[9];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      const double k2 = kk[i * 3 + 0] * kk[0 * 3 + j] + kk[i * 3 + 1] * kk[1 * 3 + j] + kk[i * 3 + 2] * kk[2 * 3 + j];
      jl[i * 3 + j] = (i == j ? 1.0 : 0.0) - 0.5 * kk[i * 3 + j] + c * k2;
    }
  }
  for (int p = 0; p < 2 * N; ++p) {
    for (int r = 0; r < 3; ++r) {
      jac[r * P + p] = -cv[p][r];
      jac[(3 + r) * P + p] = 0.0;
    }
  }
  for (int p = 2 * N; p < P; ++p) {
    const double* v = cv[p];
    const double* w = cw[p];
    const double hp[3] = {v[0] + (w[1] * ep[2] - w[2] * ep[1]), v[1] + (w[2] * ep[0] - w[0] * ep[2]),
                          v[2] + (w[0] * ep[1] - w[1] * ep[0])};
    for (int r = 0; r < 3; ++r) {
      jac[r * P + p] = -hp[r];
      jac[(3 + r) * P + p] = -(jl[r * 3 + 0] * w[0] + jl[r * 3 + 1] * w[1] + jl[r * 3 + 2] * w[2]);
    }
  }
  return true;
}

// One sample's residual block: 6 rows, the 28 parameters.
class AnalyticResidual : public ceres::SizedCostFunction<6, P> {
 public:
  AnalyticResidual(const Dataset* data, int s, TwistTrig* trig) : data_(data), s_(s), trig_(trig) {}

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
    const double* x = parameters[0];
    return analytic_sample(*data_, s_, x, trig_->sa_ca(x), residuals, jacobians != nullptr ? jacobians[0] : nullptr);
  }

 private:
  const Dataset* data_;
  int s_;
  TwistTrig* trig_;
};

// ---------------------------------------------------------------------------------------------
// Solving and timing

double cpu_now() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

double wall_now() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

struct Tolerances {
  double ftol = 1e-12, ptol = 1e-12, gtol = 1e-14;
};

struct Run {
  std::array<double, P> x;
  ceres::Solver::Summary summary;
  double solve_cpu = 0.0;
};

Run solve(const Dataset& data, const std::string& variant, const Tolerances& tol, bool verbose) {
  Run run;
  run.x = data.start;
  TwistTrig trig;
  ceres::Problem::Options popts;
  popts.disable_all_safety_checks = true;
  const bool autodiff = variant == "autodiff";
  if (!autodiff) popts.evaluation_callback = &trig;
  ceres::Problem problem(popts);
  problem.AddParameterBlock(run.x.data(), P);
  for (int s = 0; s < data.k; ++s) {
    ceres::CostFunction* cost;
    if (autodiff) {
      cost = new ceres::AutoDiffCostFunction<AutodiffResidual, 6, P>(new AutodiffResidual{&data, s});
    } else {
      cost = new AnalyticResidual(&data, s, &trig);
    }
    problem.AddResidualBlock(cost, nullptr, run.x.data());
  }
  ceres::Solver::Options opts;
  opts.linear_solver_type = ceres::DENSE_NORMAL_CHOLESKY;
  opts.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  opts.jacobi_scaling = true;
  opts.num_threads = 1;
  opts.max_num_iterations = 100;
  opts.function_tolerance = tol.ftol;
  opts.parameter_tolerance = tol.ptol;
  opts.gradient_tolerance = tol.gtol;
  opts.logging_type = verbose ? ceres::PER_MINIMIZER_ITERATION : ceres::SILENT;
  opts.minimizer_progress_to_stdout = false;
  const double c0 = cpu_now();
  ceres::Solve(opts, &problem, &run.summary);
  run.solve_cpu = cpu_now() - c0;
  if (verbose) std::fprintf(stderr, "%s\n", run.summary.FullReport().c_str());
  return run;
}

// Sum of squared pose errors and the paper's y (sum of |e|), in double.
std::pair<double, double> cost_and_y(const Dataset& data, const double* x) {
  double cost = 0.0, y = 0.0;
  for (int s = 0; s < data.k; ++s) {
    double e[6];
    if (!residual(x, data, s, e)) return {NAN, NAN};
    double n2 = 0.0;
    for (double v : e) n2 += v * v;
    cost += n2;
    y += std::sqrt(n2);
  }
  return {cost, y};
}

std::string list(const double* v, size_t n) {
  std::string out = "[";
  char buf[40];
  for (size_t i = 0; i < n; ++i) {
    std::snprintf(buf, sizeof buf, "%s%.17g", i ? "," : "", v[i]);
    out += buf;
  }
  return out + "]";
}

std::string escape(const std::string& s) {
  std::string out;
  for (char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      out += ' ';
    } else {
      out += c;
    }
  }
  return out;
}

// The analytic Jacobian against Ceres' autodiff at the start, over the first samples.
double jacobian_check(const Dataset& data) {
  TwistTrig trig;
  const double* params[1] = {data.start.data()};
  double worst = 0.0;
  for (int s = 0; s < std::min(data.k, 200); ++s) {
    AnalyticResidual analytic(&data, s, &trig);
    ceres::AutoDiffCostFunction<AutodiffResidual, 6, P> autodiff(new AutodiffResidual{&data, s});
    double ea[6], eb[6], ja[6 * P], jb[6 * P];
    double* jas[1] = {ja};
    double* jbs[1] = {jb};
    if (!analytic.Evaluate(params, ea, jas) || !autodiff.Evaluate(params, eb, jbs)) return NAN;
    for (int i = 0; i < 6 * P; ++i) worst = std::max(worst, std::abs(ja[i] - jb[i]));
    for (int i = 0; i < 6; ++i) worst = std::max(worst, std::abs(ea[i] - eb[i]));
  }
  return worst;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> dirs;
  std::vector<std::string> variants = {"analytic", "autodiff"};
  int repeats = 5;
  Tolerances tol;
  bool verbose = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) die(a + " needs a value");
      return argv[++i];
    };
    if (a == "--repeats") {
      repeats = std::max(1, std::atoi(value().c_str()));
    } else if (a == "--variants") {
      variants.clear();
      std::stringstream ss(value());
      std::string v;
      while (std::getline(ss, v, ',')) {
        if (v.empty()) continue;
        if (v != "analytic" && v != "autodiff") die("unknown variant `" + v + "`; known: analytic, autodiff");
        variants.push_back(v);
      }
    } else if (a == "--ftol") {
      tol.ftol = number(value(), "--ftol");
    } else if (a == "--ptol") {
      tol.ptol = number(value(), "--ptol");
    } else if (a == "--gtol") {
      tol.gtol = number(value(), "--gtol");
    } else if (a == "--verbose") {
      verbose = true;
    } else if (a.rfind("--", 0) == 0) {
      die("unknown option " + a);
    } else {
      dirs.push_back(a);
    }
  }
  if (dirs.empty()) die("usage: ceres_ls DIR... [--repeats N] [--variants analytic,autodiff]");
  for (const auto& dir : dirs) {
    const Dataset data = load(dir);
    const auto [cost_start, y_start] = cost_and_y(data, data.start.data());
    std::printf(
        "{\"bench\":\"ceres-check\",\"k\":%d,\"ceres\":\"%s\",\"eigen\":\"%d.%d.%d\",\"cost_start\":%.17g,"
        "\"y_start\":%.17g,\"jac_max_abs_diff\":%.3g,\"ftol\":%g,\"ptol\":%g,\"gtol\":%g}\n",
        data.k, CERES_VERSION_STRING, EIGEN_WORLD_VERSION, EIGEN_MAJOR_VERSION, EIGEN_MINOR_VERSION, cost_start,
        y_start, jacobian_check(data), tol.ftol, tol.ptol, tol.gtol);
    std::fflush(stdout);
    for (const auto& variant : variants) {
      std::vector<double> cpu, wall, solve_cpu;
      Run last;
      for (int r = 0; r < repeats; ++r) {
        const double c0 = cpu_now(), w0 = wall_now();
        Run run = solve(data, variant, tol, verbose && r == 0);
        cpu.push_back(cpu_now() - c0);
        wall.push_back(wall_now() - w0);
        solve_cpu.push_back(run.solve_cpu);
        last = std::move(run);
      }
      const auto [cost, y] = cost_and_y(data, last.x.data());
      double err[4] = {0, 0, 0, 0}, norm = 0.0;
      for (int p = 0; p < P; ++p) {
        const double d = last.x[p] - data.truth[p];
        err[p / N] = std::max(err[p / N], std::abs(d));
        norm += d * d;
      }
      const auto& s = last.summary;
      std::printf(
          "{\"bench\":\"ceres\",\"variant\":\"%s\",\"k\":%d,\"median_s\":%.6e,\"runs_s\":%s,\"wall_median_s\":%.6e,"
          "\"solve_median_s\":%.6e,\"iterations\":%d,\"successful_steps\":%d,\"jacobian_evaluations\":%d,"
          "\"residual_evaluations\":%d,\"termination\":\"%s\",\"message\":\"%s\",\"cost\":%.17g,\"y\":%.17g,"
          "\"err_a\":%.6e,\"err_d\":%.6e,\"err_alpha\":%.6e,\"err_theta\":%.6e,\"err_norm\":%.6e,"
          "\"jacobian_evaluation_s\":%.6e,\"residual_evaluation_s\":%.6e,\"linear_solver_s\":%.6e,"
          "\"minimizer_s\":%.6e,\"x\":%s}\n",
          variant.c_str(), data.k, median(cpu), list(cpu.data(), cpu.size()).c_str(), median(wall), median(solve_cpu),
          static_cast<int>(s.iterations.size()), s.num_successful_steps, s.num_jacobian_evaluations,
          s.num_residual_evaluations, ceres::TerminationTypeToString(s.termination_type),
          escape(s.message).c_str(), cost, y, err[0], err[1], err[2], err[3], std::sqrt(norm),
          s.jacobian_evaluation_time_in_seconds, s.residual_evaluation_time_in_seconds,
          s.linear_solver_time_in_seconds, s.minimizer_time_in_seconds, list(last.x.data(), P).c_str());
      std::fflush(stdout);
    }
  }
  return 0;
}
