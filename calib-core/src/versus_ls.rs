//! Our EM's table against LS's: a Hausman test in the table-error metric.
//!
//! Contract: LS from nominal is consistent whatever the drift does (it weighs the drift as
//! white noise; its error is the sandwich [`ls_expected_table_error`] at the drift and noise the
//! EM fitted), our EM is consistent and the more efficient only while its model holds. Where
//! both hold, the two tables differ by about `√(L² − S²)` (RMS over the poses the error is
//! stated on; `L` LS's expected error, `S` the EM's stated one): [`EmVersusLs::statistic`] is
//! the squared difference over that, about 1, in position and rotation (the larger counts).
//! Above [`MAX_EM_LS_STATISTIC`] the EM's model does not hold for the session where LS does not
//! need it, and its stated error is not to be believed: the caller keeps LS's table, stated by
//! `L`.
//!
//! What it catches (measured through the daemon, a wrist kept to 60 % of its range, the drift
//! in the reading, no pose noise, seed 13 of `good_enough`): the EM's table 4.7 mm off with
//! ±1.3 mm stated (its linearisation about the reported angles lets two joints' drift stand in
//! for the wrist's geometry: τ 1.9 and 2.7 s fitted where the drift has 1 s), LS's 1.0 mm off
//! with `L` = 2.4 mm; the statistic is 16. Where the EM's model holds it is 0.66–2.95 (24
//! simulated sessions, `where_the_model_holds_the_em_agrees_with_ls`).
//! Under the model the statistic is a weighted sum of χ² variables of mean 1; 4 is beyond its
//! 95th percentile for any number of them.

use crate::drift_em::{DriftEmResult, Refusal};
use crate::metrics::{ls_expected_table_error, ls_response, table_error, ErrorPoses, TableError};
use crate::model::{DhTable, Sample};

/// What to push and state, of the EM's table and LS's ([`EmVersusLs::choice`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TableChoice {
    /// The EM's table, stated by the EM: its model explains LS's table.
    Em,
    /// LS's table, stated by [`EmVersusLs::ls_expected`]: the EM's Gauss-Markov drift does not
    /// hold for the session, and LS does not need it.
    Ls,
    /// Neither: the EM found a rate bias, which moves LS's table by what it integrates, and its
    /// model does not explain LS's table either. Refuse ([`crate::Refusal::Unexplained`]).
    Neither,
}

/// Above this [`EmVersusLs::statistic`], the EM's table is not consistent with LS's.
pub const MAX_EM_LS_STATISTIC: f64 = 4.0;

/// The EM's table against LS's ([`em_versus_ls`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EmVersusLs {
    /// RMS difference of LS's table from the one the EM's model predicts for it (the EM's
    /// table moved by its fitted rate bias, [`EmVersusLs::rate_bias_shift`]) over the poses.
    pub difference: TableError,
    /// What the EM's fitted rate bias moves LS's table by (zero without one): LS takes the
    /// integrated bias into the table, the EM models it.
    pub rate_bias_shift: TableError,
    /// LS's expected table error over the same poses (the sandwich at the EM's drift and noise).
    pub ls_expected: TableError,
    /// The squared difference over what the model lets it be, `D² / max(L² − S², L²/4)` (`D² /
    /// (L² + S²)` where the EM fitted a rate bias), the larger of position and rotation.
    pub statistic: f64,
    /// Whether the EM's model has a rate bias (its table then predicts LS's moved by
    /// [`EmVersusLs::rate_bias_shift`]).
    pub rate_bias: bool,
}

impl EmVersusLs {
    /// Whether the EM's table is consistent with LS's ([`MAX_EM_LS_STATISTIC`]).
    pub fn agrees(&self) -> bool {
        self.statistic <= MAX_EM_LS_STATISTIC
    }

    /// Which table to push: the EM's where the two agree; where not, LS's unless the EM found a
    /// rate bias, which LS's table carries unmodelled (then neither).
    pub fn choice(&self) -> TableChoice {
        match (self.agrees(), self.rate_bias) {
            (true, _) => TableChoice::Em,
            (false, false) => TableChoice::Ls,
            (false, true) => TableChoice::Neither,
        }
    }

    /// The refusal to give for [`TableChoice::Neither`]: the joints with a rate bias in `em`.
    pub fn refusal<const N: usize>(&self, em: &DriftEmResult<N>) -> Option<Refusal> {
        (self.choice() == TableChoice::Neither).then(|| {
            // The joints whose rate bias is more than twice its standard error (every joint
            // with one has it, the intensities being shared), or all of those if none is.
            let significant = |j: usize| libm::fabs(em.models[j].angle) > 2.0 * em.models[j].angle_se;
            let with = |j: usize| em.rate_bias[j].iter().any(|c| *c != 0.0);
            let any_significant = (0..N).any(|j| with(j) && significant(j));
            let (mut joints, mut rate) = (0u32, 0.0f64);
            for j in 0..N {
                if with(j) && (significant(j) || !any_significant) {
                    joints |= 1 << j;
                }
                for r in em.models[j].rate {
                    if libm::fabs(r) > libm::fabs(rate) {
                        rate = r;
                    }
                }
            }
            Refusal::Unexplained {
                joints,
                rate,
                statistic: self.statistic,
            }
        })
    }
}

/// Our EM's result `em` against the LS table `ls`, both fitted on `samples`, over `poses` (the
/// ones `em` stated its error on: `DriftEmOptions::error_poses`). `None` when LS's expected
/// error cannot be computed (its normal equations too ill-conditioned).
pub fn em_versus_ls<const N: usize, const P: usize>(
    ls: &DhTable<N>,
    em: &DriftEmResult<N>,
    samples: &[Sample<N>],
    poses: &ErrorPoses<N>,
) -> Option<EmVersusLs> {
    let drift_var: [f64; N] = core::array::from_fn(|j| em.process_variance[j] / (1.0 - em.phi[j] * em.phi[j]));
    let l = ls_expected_table_error::<N, P>(ls, samples, &em.phi, &drift_var, &em.measurement_variance, poses.of(samples))?;
    // Where the EM fitted a rate bias, LS's table is expected where the EM's table moved by
    // it lies: LS counts the integrated bias as part of the geometry.
    let predicted = if em.rate_bias.iter().flatten().any(|c| *c != 0.0) {
        let shift = ls_response::<N, P>(&em.table, samples, |k| em.rate_bias_at(k, samples.len()))?;
        em.table.perturbed(&shift)
    } else {
        em.table
    };
    let d = table_error(ls, &predicted, poses.of(samples));
    let s = em.stated_error;
    // Where both hold, LS's table is more variable than the EM's by `L² − S²` (the EM is the
    // efficient one). Where the EM fitted a rate bias, its prediction of LS's table carries the
    // rate bias's own error too, which neither figure holds, and the EM's stated error (the rate
    // bias integrated out) may exceed LS's sandwich (the rate bias fixed): the two are then
    // taken as independent, `L² + S²`.
    let modelled = em.rate_bias.iter().flatten().any(|c| *c != 0.0);
    let ratio = |d: f64, l: f64, s: f64| {
        let spread = if modelled {
            l * l + s * s
        } else {
            (l * l - s * s).max(0.25 * l * l)
        };
        d * d / spread
    };
    Some(EmVersusLs {
        difference: d,
        rate_bias_shift: table_error(&em.table, &predicted, poses.of(samples)),
        ls_expected: l,
        statistic: ratio(d.position_m, l.position_m, s.position_m).max(ratio(d.rotation_rad, l.rotation_rad, s.rotation_rad)),
        rate_bias: modelled,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::JointRanges;
    use crate::sweep::{field_cell, Simulation};
    use crate::{em_drift_vec, identify_ls, DriftEmOptions, LsOptions, SUIT_PARAMS};

    const SEEDS: u64 = 8;
    const LAZY: [f64; 7] = [1.0, 1.0, 1.0, 1.0, 0.6, 0.6, 0.6];

    /// The EM's and LS's tables of `sim`'s session, the readings separated first as the daemon
    /// does (`separated`) or not, and the test of one against the other; with the real error
    /// of each.
    fn session(sim: &Simulation, separated: bool) -> (EmVersusLs, TableError, TableError) {
        let opts = DriftEmOptions {
            error_poses: ErrorPoses::Ranges(JointRanges::paper()),
            ..DriftEmOptions::new(sim.drift.dt)
        };
        let mut samples = sim.samples.clone();
        if separated {
            let mut slots = std::vec![crate::SeparationSlot::default(); samples.len()];
            crate::separate(
                &mut samples,
                &DhTable::paper_nominal(),
                sim.drift.dt,
                opts.initial_tau,
                &mut slots,
            );
        }
        let ls = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), &samples, &LsOptions::new())
            .unwrap()
            .table;
        let (em, _) = em_drift_vec::<7, SUIT_PARAMS>(&ls, &samples, &opts).unwrap();
        let v = em_versus_ls::<7, SUIT_PARAMS>(&ls, &em, &samples, &opts.error_poses).unwrap();
        let ratio = |real: TableError, stated: TableError| TableError {
            position_m: real.position_m / stated.position_m,
            rotation_rad: real.rotation_rad / stated.rotation_rad,
        };
        (
            v,
            ratio(sim.table_error(&em.table), em.stated_error),
            ratio(sim.table_error(&ls), v.ls_expected),
        )
    }

    /// A heading the EM found (0.05 °/s on joints 1, 3, 5, 60 s) moves LS's table by tens of
    /// millimetres: compared as they are (LS's table against the EM's, `D² / (L² − S²)`) the
    /// statistic would be 108–405 on 7 of 8 seeds and LS's table pushed 5.7–29 mm off at
    /// ±2–3 mm stated; with LS's table predicted from the EM's moved by the fitted rate bias,
    /// the two agree (measured 0.1–1.3) and the EM's table is kept. A LS table off by what the
    /// rate bias does not explain is refused, naming the joints with a rate bias.
    #[test]
    fn a_heading_the_em_found_explains_ls_and_an_unexplained_one_is_refused() {
        let cell = field_cell("heading 0.05 °/s on joints 1, 3, 5 (60 s)").unwrap();
        for seed in 1..=4 {
            let sim = Simulation::new(&cell, seed);
            let (v, e, _) = session(&sim, true);
            assert!(v.rate_bias, "seed {seed}: no rate bias found");
            assert_eq!(v.choice(), TableChoice::Em, "seed {seed}: {v:?}");
            assert!(
                v.rate_bias_shift.position_m > 3.0 * v.ls_expected.position_m,
                "seed {seed}: {v:?}"
            );
            assert!(
                e.position_m < 2.0 && e.rotation_rad < 2.0,
                "seed {seed}: EM real ÷ stated {e:?}"
            );
        }
        // LS's table 20 mrad off on joint 2's θ besides: the rate bias does not explain it.
        let sim = Simulation::new(&cell, 1);
        let opts = DriftEmOptions {
            error_poses: ErrorPoses::Ranges(JointRanges::paper()),
            ..DriftEmOptions::new(sim.drift.dt)
        };
        let samples = sim.separated(&sim.samples);
        let ls = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), &samples, &LsOptions::new())
            .unwrap()
            .table;
        let (em, _) = em_drift_vec::<7, SUIT_PARAMS>(&ls, &samples, &opts).unwrap();
        let mut off = ls;
        *off.param_mut(3 * 7 + 1) += 0.02;
        let v = em_versus_ls::<7, SUIT_PARAMS>(&off, &em, &samples, &opts.error_poses).unwrap();
        assert_eq!(v.choice(), TableChoice::Neither, "{v:?}");
        let why = std::format!("{}", v.refusal(&em).unwrap());
        assert!(why.contains("joints 1, 3, 5"), "{why}");
    }

    /// Where the EM's model holds (the drift in the reading separated first, as the daemon
    /// does; full reach and a lazy wrist, 8 seeds each) its table agrees with LS's: measured
    /// statistic 0.80–2.95 over these 16 sessions (0.66–2.95 over seeds 1–12), against the
    /// limit of 4.
    #[test]
    fn where_the_model_holds_the_em_agrees_with_ls() {
        let cell = field_cell("drift in the reading (60 s)").unwrap();
        for reach in [LAZY, [1.0; 7]] {
            for seed in 1..=SEEDS {
                let (v, _, _) = session(&Simulation::reaching(&cell, seed, reach), true);
                assert!(v.agrees(), "reach {reach:?} seed {seed}: statistic {:.2}", v.statistic);
            }
        }
    }

    /// Where it does not (the same sessions' readings fitted as they come: the drift in the
    /// reading is then not the EM's model, and on a lazy wrist its table is 2.6–3.9× the error
    /// it states), the test says so in most sessions (measured: 6 of 8 above 4, the other two
    /// at 3.98 and 4.0), and LS's table is within what LS's sandwich states (RMS over the
    /// sessions).
    #[test]
    fn where_it_does_not_the_em_disagrees_with_ls_and_ls_is_stated_honestly() {
        let cell = field_cell("drift in the reading (60 s)").unwrap();
        let (mut flagged, mut em, mut ls) = (0, (0.0, 0.0), (0.0, 0.0));
        for seed in 1..=SEEDS {
            let (v, e, l) = session(&Simulation::reaching(&cell, seed, LAZY), false);
            flagged += usize::from(!v.agrees());
            em = (em.0 + e.position_m.powi(2), em.1 + e.rotation_rad.powi(2));
            ls = (ls.0 + l.position_m.powi(2), ls.1 + l.rotation_rad.powi(2));
        }
        let n = SEEDS as f64;
        let (em, ls) = ((em.0 / n).sqrt(), ((ls.0 / n).sqrt(), (ls.1 / n).sqrt()));
        assert!(em > 2.0, "the EM's model fails here: real ÷ stated {em:.2}");
        assert!(flagged >= 5, "{flagged} of {SEEDS} flagged");
        assert!(ls.0 <= 1.0 && ls.1 <= 1.0, "LS real ÷ its sandwich {:.2} / {:.2}", ls.0, ls.1);
    }
}
