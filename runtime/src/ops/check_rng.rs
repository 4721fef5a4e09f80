//! The seeded generator of the on-target checks (`kernel-check` feature):
//! xorshift64, so the firmware draws the same cases on every run.

/// xorshift64 state; never 0.
pub(crate) struct Rng(pub(crate) u64);

impl Rng {
    pub(crate) fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    pub(crate) fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }

    /// Mostly uniform in `lo..lo + span`, one time in four an end.
    pub(crate) fn edgy(&mut self, lo: i64, span: u64) -> i64 {
        match self.below(8) {
            0 => lo,
            1 => lo + span as i64 - 1,
            _ => lo + self.below(span) as i64,
        }
    }
}
