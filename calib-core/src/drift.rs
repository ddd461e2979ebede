//! The first-order Gauss-Markov drift model of eqs. (7)–(8) (paper note 6).
//!
//! The joint-angle error follows `x_{k+1} = φ x_k + ρ_k`, `φ = e^{−Δt/τ}`, with
//! * [`Discretisation::Paper`] (default, the paper's eq. 8): `Var ρ = Δt²·σ²·(1 − φ)`, whose
//!   stationary deviation is `Δt·σ/√(1 + φ)` (≈ 0.00707 rad for Δt = 0.01 s, τ = 1 s, σ = 1);
//! * [`Discretisation::Exact`]: `Var ρ = σ²·(1 − φ²)`, the exact discretisation of a
//!   continuous Gauss-Markov process of stationary deviation σ (here σ is in radians).

use crate::rng::Rng;

/// How the process variance is derived from (Δt, τ, σ).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Discretisation {
    /// The paper's eq. (8): `Var ρ = Δt²σ²(1 − e^{−Δt/τ})`.
    #[default]
    Paper,
    /// Exact: `Var ρ = σ²(1 − e^{−2Δt/τ})`.
    Exact,
}

/// A first-order Gauss-Markov process, discretised at a fixed step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GaussMarkov {
    /// Sample period Δt (s).
    pub dt: f64,
    /// Correlation time τ (s).
    pub tau: f64,
    /// The σ of eq. (7)/(8) (meaning depends on `discretisation`).
    pub sigma: f64,
    /// Which variance formula.
    pub discretisation: Discretisation,
}

impl GaussMarkov {
    /// The paper's Section 4 drift: Δt = 0.01 s, τ = 1 s, σ = 1, paper discretisation.
    pub fn paper() -> Self {
        GaussMarkov {
            dt: 0.01,
            tau: 1.0,
            sigma: 1.0,
            discretisation: Discretisation::Paper,
        }
    }

    /// `φ = e^{−Δt/τ}`.
    pub fn phi(&self) -> f64 {
        libm::exp(-self.dt / self.tau)
    }

    /// Variance of the driving noise ρ_k.
    pub fn process_variance(&self) -> f64 {
        let phi = self.phi();
        match self.discretisation {
            Discretisation::Paper => self.dt * self.dt * self.sigma * self.sigma * (1.0 - phi),
            Discretisation::Exact => self.sigma * self.sigma * (1.0 - phi * phi),
        }
    }

    /// Stationary variance `q / (1 − φ²)` of the angle error.
    pub fn stationary_variance(&self) -> f64 {
        let phi = self.phi();
        self.process_variance() / (1.0 - phi * phi)
    }

    /// A draw from the stationary distribution.
    pub fn initial(&self, rng: &mut Rng) -> f64 {
        libm::sqrt(self.stationary_variance()) * rng.normal()
    }

    /// One step `φ x + ρ`.
    pub fn step(&self, x: f64, rng: &mut Rng) -> f64 {
        self.phi() * x + libm::sqrt(self.process_variance()) * rng.normal()
    }
}

/// (τ, σ) recovered from a discrete (φ, q) pair, in both conventions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftParams {
    /// Correlation time τ = −Δt / ln φ (s).
    pub tau: f64,
    /// Stationary deviation of the angle error, `√(q/(1−φ²))` (rad).
    pub stationary_sigma: f64,
    /// The paper's σ of eq. (8), `√(q / (Δt²(1−φ)))`.
    pub paper_sigma: f64,
}

impl DriftParams {
    /// Converts a discrete AR(1) `(φ, q)` at step `dt`.
    pub fn from_discrete(phi: f64, q: f64, dt: f64) -> Self {
        DriftParams {
            tau: -dt / libm::log(phi),
            stationary_sigma: libm::sqrt(q / (1.0 - phi * phi)),
            paper_sigma: libm::sqrt(q / (dt * dt * (1.0 - phi))),
        }
    }
}

/// A rate bias integrated into a joint's angle error, as an IMU's gyro bias left after fusion
/// gives it: `c_{k+1} = c_k + Δt·b_k`, `b_{k+1} = b_k + walk·√Δt·N(0, 1)`, `c_0 = 0` at the
/// session's start, `b_0 ~ N(0, ramp²)`, independently per joint. The simulator draws it
/// ([`crate::sim`]); [`crate::DriftEmOptions::rate_bias_spec`] takes the sensors' spec in the same
/// terms.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RateBias {
    /// Standard deviation of each joint's rate bias at the start (rad/s); alone, a ramp.
    pub ramp: f64,
    /// Intensity of the bias's random walk (rad/s/√s): it wanders by `walk·√t` in t seconds.
    pub walk: f64,
}

impl RateBias {
    /// No rate bias.
    pub const NONE: RateBias = RateBias { ramp: 0.0, walk: 0.0 };

    /// Whether there is any.
    pub fn is_none(&self) -> bool {
        self.ramp == 0.0 && self.walk == 0.0
    }

    /// The variances (rad²) of the coefficients of `s` and `s²` (`s` the fraction of a session
    /// of `seconds`) that represent it: `(ramp·T)² + walk²·T³/3` and `walk²·T³/3` (the walk's
    /// angle at the session's end, `walk²·T³/3`, shared by both terms).
    pub fn intensities(&self, seconds: f64) -> [f64; 2] {
        let walk = self.walk * self.walk * seconds * seconds * seconds / 3.0;
        [self.ramp * self.ramp * seconds * seconds + walk, walk]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_stationary_deviation_is_about_7_mrad() {
        let gm = GaussMarkov::paper();
        let s = libm::sqrt(gm.stationary_variance());
        assert!((s - 0.00707).abs() < 5e-5, "{s}");
        let exact = GaussMarkov {
            discretisation: Discretisation::Exact,
            sigma: 0.01,
            ..gm
        };
        assert!((libm::sqrt(exact.stationary_variance()) - 0.01).abs() < 1e-12);
    }

    #[test]
    fn simulated_process_has_the_model_moments_and_params_round_trip() {
        let gm = GaussMarkov::paper();
        let mut rng = Rng::new(7);
        let mut x = gm.initial(&mut rng);
        let (mut s00, mut s10, mut s11) = (0.0, 0.0, 0.0);
        for _ in 0..200_000 {
            let nx = gm.step(x, &mut rng);
            s00 += x * x;
            s10 += nx * x;
            s11 += nx * nx;
            x = nx;
        }
        let phi = s10 / s00;
        let q = (s11 - phi * s10) / 200_000.0;
        assert!((phi - gm.phi()).abs() < 2e-3, "{phi}");
        let p = DriftParams::from_discrete(phi, q, gm.dt);
        assert!((p.paper_sigma - 1.0).abs() < 0.05, "{p:?}");
        let exact = DriftParams::from_discrete(gm.phi(), gm.process_variance(), gm.dt);
        assert!((exact.tau - 1.0).abs() < 1e-12 && (exact.paper_sigma - 1.0).abs() < 1e-12);
    }
}
