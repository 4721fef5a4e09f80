//! Gate coefficients of the experts for a phase, in Q16 (65536 = 1.0).
//! The coefficients of a gate always sum to exactly 65536, so a constant
//! passes through the blend unchanged.

use super::phase::Phase;
use super::round_shift;
use super::softmax::softmax_q16;
use crate::blob::Gating;
use crate::error::Result;
use fixed::types::I16F16;

/// Most experts active in one frame (a softmax gate's every expert).
pub const MAX_ACTIVE: usize = 8;
/// Q16 one.
pub const ONE: i32 = 1 << 16;

/// The active experts of one frame and their Q16 coefficients.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Gate {
    len: u8,
    experts: [u16; MAX_ACTIVE],
    weights: [i32; MAX_ACTIVE],
}

impl Gate {
    /// Expert 0 alone, for ungated layers.
    pub const SINGLE: Gate = Gate {
        len: 1,
        experts: [0; MAX_ACTIVE],
        weights: [ONE, 0, 0, 0, 0, 0, 0, 0],
    };

    /// The gate of a softmax gate node: the Q16 softmax of `logits`
    /// (Q`frac`, at most [`crate::MAX_LOGITS`] of them), every expert active.
    pub fn softmax(logits: &[i16], frac: u8) -> Result<Gate> {
        let mut weights = [0i32; MAX_ACTIVE];
        softmax_q16(logits, frac, &mut weights)?;
        Ok(Gate {
            len: logits.len() as u8,
            experts: [0, 1, 2, 3, 4, 5, 6, 7],
            weights,
        })
    }

    /// The gate of `gating` at `phase`. Panic-free for any gating value:
    /// a zero count is treated as one expert; `Softmax`, which no phase
    /// drives, gives [`Gate::SINGLE`].
    pub fn new(gating: &Gating, phase: Phase) -> Gate {
        let p = u64::from(phase.to_bits());
        match *gating {
            Gating::Single | Gating::Softmax { .. } => Gate::SINGLE,
            Gating::Constant { tables } => {
                let s = p * u64::from(tables.max(1));
                Gate::one((s >> 32) as u16)
            }
            Gating::Linear { tables } => {
                let t = tables.max(1);
                let s = p * u64::from(t);
                let k = (s >> 32) as u16;
                let mu = ((s >> 16) & 0xFFFF) as i32;
                Gate::of([(k, ONE - mu), (next(k, 1, t), mu)])
            }
            Gating::CatmullRom { points } => catmull_rom(p, points.max(1)),
        }
    }

    fn one(expert: u16) -> Gate {
        Gate::of([(expert, ONE)])
    }

    /// The gate of `K <= MAX_ACTIVE` (expert, Q16 coefficient) pairs.
    fn of<const K: usize>(pairs: [(u16, i32); K]) -> Gate {
        let mut g = Gate {
            len: K.min(MAX_ACTIVE) as u8,
            experts: [0; MAX_ACTIVE],
            weights: [0; MAX_ACTIVE],
        };
        for ((e, w), (ge, gw)) in pairs
            .into_iter()
            .zip(g.experts.iter_mut().zip(g.weights.iter_mut()))
        {
            (*ge, *gw) = (e, w);
        }
        g
    }

    /// Number of active experts.
    pub fn len(&self) -> usize {
        usize::from(self.len).min(MAX_ACTIVE)
    }

    /// Never true; for clippy's `len_without_is_empty`.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Active experts with their raw Q16 coefficients.
    pub fn iter(&self) -> impl Iterator<Item = (u16, i32)> + '_ {
        self.experts
            .iter()
            .copied()
            .zip(self.weights.iter().copied())
            .take(self.len())
    }

    /// Active experts with their coefficients as `fixed` numbers.
    pub fn iter_fixed(&self) -> impl Iterator<Item = (u16, I16F16)> + '_ {
        self.iter().map(|(e, w)| (e, I16F16::from_bits(w)))
    }
}

fn next(k: u16, by: u16, n: u16) -> u16 {
    ((u32::from(k) + u32::from(by)) % u32::from(n.max(1))) as u16
}

/// Periodic Catmull-Rom basis at `s = phase * points`; with `mu = frac(s)`
/// and `k1 = floor(s)` the coefficients of points k1-1, k1, k1+1, k1+2 are
/// `(-mu + 2mu^2 - mu^3)/2`, `(2 - 5mu^2 + 3mu^3)/2`, `(mu + 4mu^2 - 3mu^3)/2`,
/// `(mu^3 - mu^2)/2`. Computed exactly in Q60 from a Q20 `mu`, rounded once
/// to Q16; the second coefficient takes the rounding so the sum is exact.
fn catmull_rom(p: u64, points: u16) -> Gate {
    let s = p * u64::from(points);
    let k1 = (s >> 32) as u16;
    let mu = ((s >> 12) & 0xF_FFFF) as i64; // Q20
    let mu2 = mu * mu; // Q40
    let mu3 = mu2 * mu; // Q60
    let (m1, m2, m3) = (mu << 40, mu2 << 20, mu3);
    // Twice the coefficients in Q60: shifting by 45 halves and lands in Q16.
    let w0 = round_shift(-m1 + 2 * m2 - m3, 45) as i32;
    let w2 = round_shift(m1 + 4 * m2 - 3 * m3, 45) as i32;
    let w3 = round_shift(m3 - m2, 45) as i32;
    let w1 = ONE - w0 - w2 - w3;
    Gate::of([
        (next(k1, points.saturating_sub(1), points), w0),
        (k1, w1),
        (next(k1, 1, points), w2),
        (next(k1, 2, points), w3),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn exact_cr(mu: f64) -> [f64; 4] {
        [
            (-mu + 2.0 * mu * mu - mu * mu * mu) / 2.0,
            (2.0 - 5.0 * mu * mu + 3.0 * mu * mu * mu) / 2.0,
            (mu + 4.0 * mu * mu - 3.0 * mu * mu * mu) / 2.0,
            (mu * mu * mu - mu * mu) / 2.0,
        ]
    }

    #[test]
    fn catmull_rom_matches_exact_within_two_lsb() {
        let g = Gating::CatmullRom { points: 4 };
        for i in 0..20_000u64 {
            let bits = (i * 2_147_483_647 / 10_000) as u32 ^ (i as u32).wrapping_mul(2_654_435_761);
            let gate = Gate::new(&g, Phase::from_bits(bits));
            let s = f64::from(bits) / 4_294_967_296.0 * 4.0;
            let k1 = s.floor() as u16 % 4;
            let exact = exact_cr(s - s.floor());
            let sum: i32 = gate.iter().map(|(_, w)| w).sum();
            assert_eq!(sum, ONE);
            let experts: Vec<u16> = gate.iter().map(|(e, _)| e).collect();
            assert_eq!(experts, vec![(k1 + 3) % 4, k1, (k1 + 1) % 4, (k1 + 2) % 4]);
            for ((_, w), e) in gate.iter().zip(exact) {
                // mu is truncated to Q20 (slope <= 1.5 -> 0.1 LSB), one
                // rounding each, and w1 collects the others' roundings.
                assert!(
                    (f64::from(w) - e * 65536.0).abs() <= 2.0,
                    "bits {bits:#x}: {w} vs {e}"
                );
            }
        }
    }

    #[test]
    fn linear_and_constant_pick_the_demo_tables() {
        let lin = Gate::new(
            &Gating::Linear { tables: 10 },
            Phase::from_bits(0x8000_0000),
        );
        assert_eq!(lin.iter().collect::<Vec<_>>(), vec![(5, ONE), (6, 0)]);
        let lin = Gate::new(&Gating::Linear { tables: 10 }, Phase::from_bits(u32::MAX));
        let v: Vec<_> = lin.iter().collect();
        assert_eq!((v[0].0, v[1].0), (9, 0));
        let c = Gate::new(&Gating::Constant { tables: 50 }, Phase::from_bits(u32::MAX));
        assert_eq!(c.iter().collect::<Vec<_>>(), vec![(49, ONE)]);
        let c = Gate::new(&Gating::Constant { tables: 0 }, Phase::from_bits(u32::MAX));
        assert_eq!(c.iter().collect::<Vec<_>>(), vec![(0, ONE)]);
    }

    #[test]
    fn gates_never_panic_on_odd_counts() {
        for n in [0u16, 1, 2, 3, 4, 7, u16::MAX] {
            for bits in [0u32, 1, 0x7FFF_FFFF, u32::MAX] {
                let p = Phase::from_bits(bits);
                for g in [
                    Gating::Constant { tables: n },
                    Gating::Linear { tables: n },
                    Gating::CatmullRom { points: n },
                ] {
                    let gate = Gate::new(&g, p);
                    assert!(gate.iter().all(|(e, _)| e < n.max(1)));
                }
            }
        }
    }
}
