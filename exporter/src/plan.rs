//! The arena plan: an offset in one activation arena for every buffer of
//! a graph (the quantised input, each node's concatenated input, scratch
//! and output), such that buffers live at a common step never share an
//! element. Lifetimes are the runtime's own ([`phasegate::graph::buffers`]),
//! and the loader re-checks the result ([`phasegate::graph::check_plan`]).
//!
//! Placement is greedy first fit, as TFLM's planner does: each buffer goes
//! to the lowest offset clear of the buffers already placed that it meets.
//! Five orders are tried (by first use; by size; by lifetime; by size times
//! lifetime; by last use), then, while none reaches the lower bound, up to
//! 2,000 seeded shuffles; the smallest arena wins. No plan can use
//! fewer elements than the largest total of buffers live at one step
//! ([`lower_bound`]); `tests/tests/graph_model.rs` compares the two on
//! every golden model.

use phasegate::blob::{Header, Nodes, Span};
use phasegate::graph::{buffers, in_place, locate, Buffer, Role};

use crate::lower::qmodel::EncodeError;

/// Random orders tried after the five fixed ones when none reaches the
/// lower bound.
const SHUFFLES: usize = 2000;

/// Fills in the offsets of every span of `h` (whose lengths are set),
/// reading single-slice inputs in place, and the exact `ram_bytes`.
pub fn plan_arena(h: &mut Header) -> Result<(), EncodeError> {
    let bufs: Vec<Buffer> = buffers(h).into_iter().collect();
    let by_first: Vec<usize> = (0..bufs.len()).collect();
    let order = |key: &dyn Fn(&Buffer) -> (i64, i64, i64)| {
        let mut o = by_first.clone();
        o.sort_by_key(|&i| key(&bufs[i]));
        o
    };
    let len = |b: &Buffer| i64::from(b.span.len);
    let life = |b: &Buffer| (b.last - b.first) as i64;
    let orders = [
        by_first.clone(),
        order(&|b| (-len(b), b.first as i64, 0)),
        order(&|b| (-life(b), -len(b), b.first as i64)),
        order(&|b| (-(len(b) * (life(b) + 1)), b.first as i64, 0)),
        order(&|b| (-(b.last as i64), -len(b), 0)),
    ];
    let mut best = (Vec::new(), usize::MAX);
    let consider = |best: &mut (Vec<usize>, usize), order: &[usize]| {
        let (offsets, end) = first_fit(&bufs, order);
        if end < best.1 {
            *best = (offsets, end);
        }
    };
    orders.iter().for_each(|o| consider(&mut best, o));
    // Then shuffles of the first-use order, from a fixed seed (the same
    // blob on every run), until one reaches the lower bound.
    let bound = lower_bound(h);
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    for _ in 0..SHUFFLES {
        if best.1 <= bound {
            break;
        }
        let mut o = by_first.clone();
        for i in (1..o.len()).rev() {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            o.swap(i, (state % (i as u64 + 1)) as usize);
        }
        consider(&mut best, &o);
    }
    let (offsets, end) = best;
    let too_large = || EncodeError::TooLarge("activation arena");
    for (b, &offset) in bufs.iter().zip(&offsets) {
        let offset = u16::try_from(offset).map_err(|_| too_large())?;
        let node = b.role.node();
        let span: Option<&mut Span> = match b.role {
            Role::Input => Some(&mut h.input),
            Role::Concat(_) => h.nodes.get_mut(usize::from(node)).map(|n| &mut n.input),
            Role::Scratch(_) => h.nodes.get_mut(usize::from(node)).map(|n| &mut n.scratch),
            Role::Output(_) => h.nodes.get_mut(usize::from(node)).map(|n| &mut n.output),
        };
        span.ok_or_else(too_large)?.offset = offset;
    }
    for i in 0..h.nodes.len() {
        if in_place(&h.nodes[i]) {
            let at = locate(h, &h.nodes[i].inputs[0]).ok_or(EncodeError::Graph(
                phasegate::Error::GraphInvalid { node: i as u8 },
            ))?;
            h.nodes[i].input = at;
        }
    }
    h.ram_bytes = u32::try_from(2 * end).map_err(|_| too_large())?;
    Ok(())
}

/// Offsets of `bufs` placed in `order`, and the arena's length.
fn first_fit(bufs: &[Buffer], order: &[usize]) -> (Vec<usize>, usize) {
    let mut offsets = vec![usize::MAX; bufs.len()];
    let mut end = 0;
    for &i in order {
        let b = &bufs[i];
        let mut taken: Vec<(usize, usize)> = order
            .iter()
            .filter(|&&j| offsets[j] != usize::MAX && bufs[j].meets(b))
            .map(|&j| (offsets[j], offsets[j] + usize::from(bufs[j].span.len)))
            .collect();
        taken.sort_unstable();
        let len = usize::from(b.span.len);
        // A CP layer's middle vector starts on a word (an even element of
        // the 8-aligned arena): the DSP kernel's block loop reads its
        // inputs by words, and falls back to its slow tail otherwise.
        let align = |at: usize| match b.role {
            Role::Scratch(_) => at.next_multiple_of(2),
            _ => at,
        };
        let mut at = 0;
        for (start, stop) in taken {
            if at + len <= start {
                break;
            }
            at = align(at.max(stop));
        }
        offsets[i] = at;
        end = end.max(at + len);
    }
    (offsets, end)
}

/// The largest total length of buffers live at one step: no plan can use
/// fewer elements.
pub fn lower_bound<N: Nodes>(h: &Header<N>) -> usize {
    let bufs = buffers(h);
    let last = bufs.iter().map(|b| b.last).max().unwrap_or(0);
    (0..=last)
        .map(|t| {
            bufs.iter()
                .filter(|b| b.first <= t && t <= b.last)
                .map(|b| usize::from(b.span.len))
                .sum()
        })
        .max()
        .unwrap_or(0)
}
