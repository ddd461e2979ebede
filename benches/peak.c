// This core's floating-point peak in f64, measured: independent chains of vector operations,
// enough of them to cover the latencies, timed with the process CPU clock.
//
// * `sse2_mul_add`: 128-bit multiplies and adds (separate instructions, never fused): the
//   ceiling of code built for baseline x86-64, which is how Rust builds calib-core (Rust never
//   contracts a * b + c into an FMA);
// * `avx_mul_add`: the same with 256-bit vectors (code built with AVX, e.g. -C target-cpu=native);
// * `avx_fma`: 256-bit fused multiply-adds (what the silicon peaks at; a 512-bit FMA does not
//   double it on a core that splits 512-bit operations into two 256-bit halves).
//
// Flops count a multiply, an add and an FMA's multiply and add each as one. One JSON line on
// stdout: {"bench":"peak","sse2_mul_add_gflops":..,"avx_mul_add_gflops":..,"avx_fma_gflops":..}
// (the best of 25 short runs of each: on a shared core, the run least disturbed by others). Built with -O2 -march=native by `cargo xtask bench --only calib`.

#include <stdio.h>
#include <time.h>

typedef double v2 __attribute__((vector_size(16)));
typedef double v4 __attribute__((vector_size(32)));

// Eight chains of each kind (latency 3-4 cycles, two pipes per kind: six to eight chains keep
// them busy), written out so that they stay in registers.
#define EACH(S) S(0) S(1) S(2) S(3) S(4) S(5) S(6) S(7)
#define ITERS 4000000L

static double cpu_now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

// `volatile` inputs: the compiler cannot fold the arithmetic away.
static volatile double vm = 0.999999, vminv = 1.0 / 0.999999, va = 1e-6;
static volatile double sink;

// Per iteration: 8 chains x each multiplied twice, 8 chains y each added to twice.
#define MUL_ADD(V, LANES)                                      \
  static double V##_mul_add(void) {                            \
    const V m = vm - (V){}, mi = vminv - (V){}, a = va - (V){}; \
    EACH(DECL)                                                 \
    const double t0 = cpu_now();                               \
    for (long i = 0; i < ITERS; ++i) {                         \
      EACH(STEP)                                               \
    }                                                          \
    const double t = cpu_now() - t0;                           \
    V s = (V){};                                               \
    EACH(SUM)                                                  \
    sink = s[0];                                               \
    return 4.0 * 8 * LANES * ITERS / t * 1e-9;                 \
  }
#define DECL(c) V x##c = (V){} + 1.0 + c, y##c = (V){} + 1.5 + c;
#define STEP(c) x##c = x##c * m * mi; y##c = y##c + a - a;
#define SUM(c) s += x##c + y##c;
#define V v2
MUL_ADD(v2, 2)
#undef V
#define V v4
MUL_ADD(v4, 4)
#undef V

// 16 chains of 256-bit FMAs x = x * m + a (built with -ffp-contract=fast, so fused; a fixed
// point near 1: no overflow). Per iteration 2 FMAs per chain.
#define DECL2(c) v4 x##c = (v4){} + 1.0 + c, z##c = (v4){} + 1.5 + c;
#define FMA2(c) x##c = x##c * m + a; z##c = z##c * m + a; x##c = x##c * m + a; z##c = z##c * m + a;
#define SUM2(c) s += x##c + z##c;
static double v4_fma(void) {
  const v4 m = vm - (v4){}, a = va - (v4){};
  EACH(DECL2)
  const double t0 = cpu_now();
  for (long i = 0; i < ITERS; ++i) {
    EACH(FMA2)
  }
  const double t = cpu_now() - t0;
  v4 s = (v4){};
  EACH(SUM2)
  sink = s[0];
  return 2.0 * 32 * 4 * ITERS / t * 1e-9;
}

static double best(double (*f)(void)) {
  double b = 0.0;
  for (int r = 0; r < 25; ++r) {
    const double g = f();
    if (g > b) b = g;
  }
  return b;
}

int main(void) {
  const double sse2 = best(v2_mul_add), avx = best(v4_mul_add), fma = best(v4_fma);
  printf("{\"bench\":\"peak\",\"sse2_mul_add_gflops\":%.2f,\"avx_mul_add_gflops\":%.2f,\"avx_fma_gflops\":%.2f}\n", sse2,
         avx, fma);
  return 0;
}
