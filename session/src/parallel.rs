//! The LS linearisation on several cores.
//!
//! calib-core stays single-threaded and `no_std`; what it exposes is the per-sample work of an
//! LS iteration ([`calib_core::normal_equations`], [`calib_core::ls::cost`]) and a way to
//! merge it ([`GramAccumulator::merge`]). [`Parallel`] implements its [`Linearise`]: the
//! session is split into fixed blocks of [`BLOCK`] samples, each accumulated on its own, the
//! blocks spread over std scoped threads (spawned per linearisation) and merged in block order.
//! The result is the same least-squares problem as calib-core's one-pass LS, added up in
//! another order (the same optimum to the rounding of the cost, tested), and bit-identical on
//! any number of cores.
//!
//! Only the LS parallelises: the drift EM is a Kalman filter and smoother, sequential in time.

use std::num::NonZeroUsize;

use calib_core::{ls, normal_equations, DhTable, GramAccumulator, Linearise, Sample};

/// Samples per block. The blocks do not depend on the thread count, so neither does the
/// result: bit-identical on any number of cores.
pub const BLOCK: usize = 1024;

/// A session's samples, linearised in blocks of [`BLOCK`] spread over up to `threads` threads.
#[derive(Clone, Copy, Debug)]
pub struct Parallel<'a, const N: usize> {
    samples: &'a [Sample<N>],
    threads: NonZeroUsize,
}

impl<'a, const N: usize> Parallel<'a, N> {
    /// `samples` on up to `threads` threads.
    pub fn new(samples: &'a [Sample<N>], threads: NonZeroUsize) -> Self {
        Parallel { samples, threads }
    }

    /// `samples` on every core the process may use.
    pub fn on_all_cores(samples: &'a [Sample<N>]) -> Self {
        let threads = std::thread::available_parallelism().unwrap_or(NonZeroUsize::MIN);
        Parallel::new(samples, threads)
    }

    /// `work` on every block (a contiguous run of blocks per thread, the first run on this
    /// thread); the results in block order.
    fn each_block<T: Send>(&self, work: impl Fn(&[Sample<N>]) -> T + Sync) -> Vec<T> {
        let blocks: Vec<&[Sample<N>]> = self.samples.chunks(BLOCK).collect();
        let per_thread = blocks.len().div_ceil(self.threads.get()).max(1);
        let mut runs = blocks.chunks(per_thread);
        let first = runs.next().unwrap_or(&[]);
        std::thread::scope(|s| {
            let work = &work;
            let others: Vec<_> = runs
                .map(|run| s.spawn(move || run.iter().map(|b| work(b)).collect::<Vec<T>>()))
                .collect();
            let mut out: Vec<T> = first.iter().map(|b| work(b)).collect();
            for handle in others {
                // A panic in a block is a bug in the work itself: let it carry on.
                out.extend(
                    handle
                        .join()
                        .unwrap_or_else(|p| std::panic::resume_unwind(p)),
                );
            }
            out
        })
    }
}

impl<const N: usize, const P: usize> Linearise<N, P> for Parallel<'_, N> {
    fn normal_equations(&self, table: &DhTable<N>, out: &mut GramAccumulator<P>) -> f64 {
        let blocks = self.each_block(|block| {
            let mut acc = GramAccumulator::<P>::new();
            let cost = normal_equations(table, block, &mut acc);
            (acc, cost)
        });
        let mut total = 0.0;
        for (acc, cost) in &blocks {
            out.merge(acc);
            total += cost;
        }
        total
    }

    fn cost(&self, table: &DhTable<N>) -> f64 {
        self.each_block(|block| ls::cost(table, block))
            .into_iter()
            .fold(0.0, |acc, c| acc + c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::{
        identify_ls, identify_ls_with, LsOptions, Scenario, ScenarioConfig, SUIT_PARAMS,
    };

    #[test]
    fn blocks_on_two_threads_reach_the_one_pass_optimum_bit_identically_to_one_thread() {
        let samples: Vec<Sample<7>> = Scenario::new(ScenarioConfig::paper(), 4)
            .take(2500)
            .map(|s| s.sample)
            .collect();
        let start = DhTable::paper_nominal();
        let opts = LsOptions::paper();
        let one = identify_ls::<7, SUIT_PARAMS>(&start, &samples, &opts).unwrap();
        let lin = Parallel::new(&samples, NonZeroUsize::new(2).unwrap());
        let two = identify_ls_with::<7, SUIT_PARAMS>(&start, &samples, &opts, &lin).unwrap();
        let lin1 = Parallel::new(&samples, NonZeroUsize::MIN);
        let one_thread =
            identify_ls_with::<7, SUIT_PARAMS>(&start, &samples, &opts, &lin1).unwrap();
        assert_eq!(two.cost.to_bits(), one_thread.cost.to_bits());
        assert_eq!(two.table, one_thread.table);
        assert!(
            (one.cost - two.cost).abs() < 1e-13 * one.cost,
            "{} vs {}",
            one.cost,
            two.cost
        );
        for p in 0..SUIT_PARAMS {
            assert!(
                (one.table.param(p) - two.table.param(p)).abs() < 1e-10,
                "param {p}"
            );
        }
    }
}
