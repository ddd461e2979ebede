//! Lines about an event that can repeat without bound, bounded.
//!
//! A frame anyone on the bus can send (a Trigger frame during a session, a valid trigger during
//! the cooldown) must not become a line each: a flood of them would trip journald's rate limit,
//! which then drops every later exocald line, refusal reasons included. [`Throttle`] gives the
//! first [`FIRST`] occurrences a line each, then the 10th, 100th, 1,000th… with the count so
//! far: `n` occurrences make at most `FIRST + log10(n)` lines, and none is silent about how
//! many there were.

/// Occurrences that get a line each before the throttle counts in powers of ten.
pub const FIRST: u64 = 3;

/// Counts the occurrences of one kind of event and says which get a line.
#[derive(Debug, Default, Clone, Copy)]
pub struct Throttle {
    seen: u64,
}

impl Throttle {
    /// Counts one occurrence; the count so far when this one gets a line.
    pub fn occur(&mut self) -> Option<u64> {
        self.seen = self.seen.saturating_add(1);
        let n = self.seen;
        (n <= FIRST || is_power_of_ten(n)).then_some(n)
    }

    /// How many occurrences were counted.
    pub fn seen(&self) -> u64 {
        self.seen
    }

    /// `line` for the `n`th occurrence: as it is for the first [`FIRST`], then with the count.
    pub fn line(line: &str, n: u64) -> String {
        if n <= FIRST {
            line.to_string()
        } else {
            format!(
                "{line} ({n} so far; the next line at {})",
                n.saturating_mul(10)
            )
        }
    }
}

fn is_power_of_ten(mut n: u64) -> bool {
    while n >= 10 && n.is_multiple_of(10) {
        n /= 10;
    }
    n == 1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The attack: a million Trigger frames in a session make 3 + 6 lines, the last saying how
    /// many.
    #[test]
    fn a_flood_makes_a_line_per_power_of_ten() {
        let mut t = Throttle::default();
        let lines: Vec<u64> = (0..1_000_000).filter_map(|_| t.occur()).collect();
        assert_eq!(lines, [1, 2, 3, 10, 100, 1_000, 10_000, 100_000, 1_000_000]);
        assert_eq!(t.seen(), 1_000_000);
        assert_eq!(Throttle::line("trigger ignored", 2), "trigger ignored");
        assert_eq!(
            Throttle::line("trigger ignored", 100),
            "trigger ignored (100 so far; the next line at 1000)"
        );
    }
}
