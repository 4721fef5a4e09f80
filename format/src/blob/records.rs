//! Fixed-size little-endian records inside payload sections.

#![deny(clippy::arithmetic_side_effects)]

/// Bytes of one requantisation record.
pub const REQUANT_RECORD_LEN: usize = 8;
/// Bytes of one input- or output-stage record (two f32).
pub const STAGE_RECORD_LEN: usize = 8;

/// Largest output-stage `|scale|` the loader accepts: 2^24.
///
/// With [`MAX_OUTPUT_OFFSET`] it bounds every output of a loaded model:
/// the output stage maps an i16 `q` (`|q| <= 2^15`) to
/// `y = q * scale + offset`, so `|y| <= 2^15 * 2^24 + 2^39 = 2^40`
/// (about 1.1e12 model units). An output that could exceed 2^40 is
/// *absurd* (no motion model has such units) and a stage that allows one
/// is refused (`UnsupportedParameter { layer: 255 }`): a loaded model's
/// outputs are always finite.
pub const MAX_OUTPUT_SCALE: f32 = 16_777_216.0;
/// Largest output-stage `|offset|` the loader accepts: 2^39 (see
/// [`MAX_OUTPUT_SCALE`]).
pub const MAX_OUTPUT_OFFSET: f32 = 549_755_813_888.0;

/// How one output row turns its blended accumulator into an i16:
/// `y = sat16(round(sat32(round(acc >> pre)) * multiplier >> post))`,
/// both roundings half up; then the activation, which reads the row's
/// value as a Q`frac` number.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Requant {
    /// Signed multiplier.
    pub multiplier: i32,
    /// Right shift applied before the multiplication (keeps it in 64 bits).
    pub pre_shift: u8,
    /// Right shift applied after it.
    pub post_shift: u8,
    /// Fraction bits of the row's output (its Q format), used by ELU.
    pub frac: u8,
}

impl Requant {
    /// Largest shift the loader accepts.
    pub const MAX_SHIFT: u8 = 62;

    /// Encodes the record (the exporter's side).
    #[inline]
    pub fn to_bytes(&self) -> [u8; REQUANT_RECORD_LEN] {
        let m = self.multiplier.to_le_bytes();
        [
            m[0],
            m[1],
            m[2],
            m[3],
            self.pre_shift,
            self.post_shift,
            self.frac,
            0,
        ]
    }

    /// Decodes a record; `None` if its reserved byte is not zero.
    #[inline]
    pub fn from_bytes(b: &[u8; REQUANT_RECORD_LEN]) -> Option<Requant> {
        let [m0, m1, m2, m3, pre_shift, post_shift, frac, reserved] = *b;
        (reserved == 0).then_some(Requant {
            multiplier: i32::from_le_bytes([m0, m1, m2, m3]),
            pre_shift,
            post_shift,
            frac,
        })
    }
}

/// Bytes of one RBF scale record.
pub const RBF_SCALE_RECORD_LEN: usize = 8;

/// How an RBF row turns its squared distance `D` into a position in the
/// exp table (`docs/graph-format.md`, "The RBF op"):
/// `pos = floor(D * multiplier / 2^shift)`, so `multiplier / 2^shift` is
/// `sigma^2` times the table's positions per real unit (`2^22`) over the
/// square of the distance's scale.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RbfScale {
    /// Unsigned multiplier.
    pub multiplier: u32,
    /// Right shift after the multiplication, at most [`RbfScale::MAX_SHIFT`].
    pub shift: u8,
}

impl RbfScale {
    /// Largest shift the loader accepts (the product is 96 bits wide).
    pub const MAX_SHIFT: u8 = 95;

    /// Encodes the record: multiplier (u32 LE), shift, three zero bytes.
    #[inline]
    pub fn to_bytes(&self) -> [u8; RBF_SCALE_RECORD_LEN] {
        let m = self.multiplier.to_le_bytes();
        [m[0], m[1], m[2], m[3], self.shift, 0, 0, 0]
    }

    /// Decodes a record; `None` if a reserved byte is set or the shift is
    /// above [`RbfScale::MAX_SHIFT`].
    #[inline]
    pub fn from_bytes(b: &[u8; RBF_SCALE_RECORD_LEN]) -> Option<RbfScale> {
        let [m0, m1, m2, m3, shift, r0, r1, r2] = *b;
        (r0 | r1 | r2 == 0 && shift <= Self::MAX_SHIFT).then_some(RbfScale {
            multiplier: u32::from_le_bytes([m0, m1, m2, m3]),
            shift,
        })
    }
}

/// Splits a stage record into its two f32 fields.
#[inline]
pub fn stage_record(b: &[u8; STAGE_RECORD_LEN]) -> (f32, f32) {
    let [a0, a1, a2, a3, b0, b1, b2, b3] = *b;
    (
        f32::from_le_bytes([a0, a1, a2, a3]),
        f32::from_le_bytes([b0, b1, b2, b3]),
    )
}

/// Reads the `i`-th bias of a section of `width`-byte little-endian integers.
#[inline]
pub fn bias_at(section: &[u8], width: usize, i: usize) -> Option<i64> {
    let start = i.checked_mul(width)?;
    let b = section.get(start..start.checked_add(width)?)?;
    match *b {
        [a, b, c, d] => Some(i64::from(i32::from_le_bytes([a, b, c, d]))),
        [a, b, c, d, e, f, g, h] => Some(i64::from_le_bytes([a, b, c, d, e, f, g, h])),
        _ => None,
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not blob input
mod tests {
    use super::*;

    #[test]
    fn requant_round_trips_and_rejects_reserved_bits() {
        let r = Requant {
            multiplier: -123_456_789,
            pre_shift: 7,
            post_shift: 40,
            frac: 9,
        };
        let mut b = r.to_bytes();
        assert_eq!(Requant::from_bytes(&b), Some(r));
        b[7] = 1;
        assert_eq!(Requant::from_bytes(&b), None);
    }

    #[test]
    fn rbf_scale_round_trips_and_rejects_reserved_bits_and_wide_shifts() {
        let r = RbfScale {
            multiplier: 0xDEAD_BEEF,
            shift: 95,
        };
        let b = r.to_bytes();
        assert_eq!(RbfScale::from_bytes(&b), Some(r));
        for (at, v) in [(5, 1), (6, 1), (7, 0x80), (4, 96)] {
            let mut c = b;
            c[at] = v;
            assert_eq!(RbfScale::from_bytes(&c), None, "byte {at} = {v}");
        }
    }

    #[test]
    fn bias_widths() {
        let s = [0xFF, 0xFF, 0xFF, 0xFF, 2, 0, 0, 0];
        assert_eq!(bias_at(&s, 4, 0), Some(-1));
        assert_eq!(bias_at(&s, 4, 1), Some(2));
        assert_eq!(bias_at(&s, 4, 2), None);
        assert_eq!(bias_at(&s, 8, 0), Some(0x0000_0002_FFFF_FFFF));
    }
}
