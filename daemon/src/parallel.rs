//! The LS linearisation on several cores.
//!
//! calib-core stays single-threaded and `no_std`; what it exposes is the per-sample work of an
//! LS iteration ([`calib_core::normal_equations`], [`calib_core::ls::cost`]) and a way to
//! merge it ([`GramAccumulator::merge`]). [`Parallel`] implements its [`Linearise`]: the
//! session is split into one contiguous block per thread (std scoped threads, spawned per
//! linearisation), each block is accumulated on its own, and the blocks are merged in block
//! order. The result is the same least-squares problem, added up in another order: the same
//! optimum to the rounding of the cost (tested), deterministic for a given thread count.
//!
//! Only the LS parallelises: the drift EM is a Kalman filter and smoother, sequential in time.

use std::num::NonZeroUsize;

use calib_core::{ls, normal_equations, DhTable, GramAccumulator, Linearise, Sample};

/// Fewest samples a block is given: below that a thread costs more than it saves.
pub const MIN_BLOCK: usize = 500;

/// A session's samples, linearised in contiguous blocks on up to `threads` threads.
#[derive(Clone, Copy, Debug)]
pub struct Parallel<'a, const N: usize> {
    samples: &'a [Sample<N>],
    threads: NonZeroUsize,
}

impl<'a, const N: usize> Parallel<'a, N> {
    /// `samples` on up to `threads` threads (one block each, at least [`MIN_BLOCK`] samples).
    pub fn new(samples: &'a [Sample<N>], threads: NonZeroUsize) -> Self {
        Parallel { samples, threads }
    }

    /// `samples` on every core the process may use.
    pub fn on_all_cores(samples: &'a [Sample<N>]) -> Self {
        let threads = std::thread::available_parallelism().unwrap_or(NonZeroUsize::MIN);
        Parallel::new(samples, threads)
    }

    /// The blocks: as many as threads, each at least [`MIN_BLOCK`] samples (at least one).
    fn block_len(&self) -> usize {
        let blocks = self
            .threads
            .get()
            .min(self.samples.len() / MIN_BLOCK)
            .max(1);
        self.samples.len().div_ceil(blocks).max(1)
    }

    /// `work` on every block, the first on this thread; the results in block order.
    fn each_block<T: Send>(&self, work: impl Fn(&[Sample<N>]) -> T + Sync) -> Vec<T> {
        let mut blocks = self.samples.chunks(self.block_len());
        let first = blocks.next().unwrap_or(&[]);
        std::thread::scope(|s| {
            let work = &work;
            let others: Vec<_> = blocks.map(|b| s.spawn(move || work(b))).collect();
            let mut out = vec![work(first)];
            for handle in others {
                // A panic in a block is a bug in the work itself: let it carry on.
                out.push(
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
    fn two_threads_reach_the_optimum_of_one() {
        let samples: Vec<Sample<7>> = Scenario::new(ScenarioConfig::paper(), 4)
            .take(2500)
            .map(|s| s.sample)
            .collect();
        let start = DhTable::paper_nominal();
        let opts = LsOptions::paper();
        let one = identify_ls::<7, SUIT_PARAMS>(&start, &samples, &opts).unwrap();
        let lin = Parallel::new(&samples, NonZeroUsize::new(2).unwrap());
        assert_eq!(lin.block_len(), 1250);
        let two = identify_ls_with::<7, SUIT_PARAMS>(&start, &samples, &opts, &lin).unwrap();
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
        // Too few samples for two blocks: one, on this thread.
        let short = Parallel::new(&samples[..700], NonZeroUsize::new(2).unwrap());
        assert_eq!(short.block_len(), 700);
    }
}
