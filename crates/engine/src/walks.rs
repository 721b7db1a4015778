//! The walks the kernels run, in one table: what each is called in its entry points, the
//! WGSL file that defines it, which arrays of the tree it reads and what it does with a
//! tree deeper than its stack. The kernel key (entry points, the files of a module), the
//! upload (which arrays go to the device, which walks an upload answers) and the trace
//! (the depth checks, the host copy that finishes rays) all read [`WALKS`]; a new walk is
//! a [`Traversal`] with its CPU twin in `bvhtrace_core`, its WGSL file in `shaders/` and
//! one row here.

use bvhtrace_core::Traversal;
use bvhtrace_core::traverse::MAX_SHORT_STACK;

use crate::error::TraceError;
use crate::shaders::{self, Wgsl};

/// Entries of the full-stack kernel's stack (`FULL_STACK_SIZE` in
/// `traverse_full_stack.wgsl`): the deepest tree the full-stack walk accepts.
pub const FULL_STACK_SIZE: u32 = 64;

/// Node groups (a node and its mask: two stack entries) the wide walk's stack holds per
/// lane (`WIDE_STACK_GROUPS` in `traverse_wide.wgsl`): a wide tree of at most this many
/// plus one levels never fills it; on a deeper one a ray that would overflow it comes back
/// incomplete and is finished on the host ([`crate::tracer::finish_incomplete`]).
pub const WIDE_STACK_GROUPS: u32 = FULL_STACK_SIZE / 2;

/// Lanes per workgroup the traversal stacks are laid out for (`STACK_LANES` in
/// `traverse_stack.wgsl`): a shader that calls a walk runs workgroups of at most this many
/// invocations and passes `local_invocation_index` as `lane`.
pub const STACK_LANES: u32 = 64;

/// Which layout of the tree a walk reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Layout {
    /// Two children per node (`FlatBvh`): nodes, triangles, instances.
    Binary,
    /// Eight compressed children per node (`WideBvh`), with its own nodes, triangles and
    /// instances.
    Wide,
}

/// What a walk does with a tree deeper than its stack.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthRule {
    /// Takes any depth: no stack, or a ring that falls back on the escape links.
    Any,
    /// Refuses a binary tree deeper than this ([`TraceError::TooDeep`]).
    Refuse(u32),
    /// A ray that would overflow the stack on a tree (of the walk's layout) deeper than
    /// this comes back incomplete, and is finished on the host copy of the tree.
    FinishOnHost(u32),
}

/// One walk of the kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Walk {
    /// Its name in the WGSL: `bvh_trace_{stem}` and its entry points.
    pub stem: &'static str,
    /// Its entry points: `[hits only, counted]`.
    pub entry_points: [&'static str; 2],
    /// How a composed module labels them (`entry_walk.wgsl` specialised).
    pub(crate) entry_labels: [&'static str; 2],
    /// The file defining `bvh_trace_{stem}`.
    pub file: Wgsl,
    /// Its call on `{ray}` for query `{any}` by lane `{lane}` (`{k}`: a short stack's
    /// size), filled in by [`Walk::call_with`].
    pub call: &'static str,
    /// The layout it reads.
    pub layout: Layout,
    /// It reads the escape links (binding 2).
    pub escapes: bool,
    /// What it does with a deep tree.
    pub depth: DepthRule,
}

/// A walk's row of [`WALKS`].
macro_rules! walk {
    ($stem:literal, $file:expr, $call:literal, $layout:expr, $escapes:expr, $depth:expr) => {
        Walk {
            stem: $stem,
            entry_points: [
                concat!("bvh_trace_", $stem, "_main"),
                concat!("bvh_trace_", $stem, "_counted"),
            ],
            entry_labels: [
                concat!("entry_walk.wgsl: bvh_trace_", $stem, "_main"),
                concat!("entry_walk.wgsl: bvh_trace_", $stem, "_counted"),
            ],
            file: $file,
            call: $call,
            layout: $layout,
            escapes: $escapes,
            depth: $depth,
        }
    };
}

/// Every walk, in the order modules compose them.
pub const WALKS: [Walk; 3] = [
    walk!(
        "full_stack",
        shaders::TRAVERSE_FULL_STACK,
        "bvh_trace_full_stack({ray}, {any}, {lane})",
        Layout::Binary,
        false,
        DepthRule::Refuse(FULL_STACK_SIZE)
    ),
    walk!(
        "short_stack",
        shaders::TRAVERSE_SHORT_STACK,
        "bvh_trace_short_stack({ray}, {any}, {k}, {lane})",
        Layout::Binary,
        true,
        DepthRule::Any
    ),
    walk!(
        "wide",
        shaders::TRAVERSE_WIDE,
        "bvh_trace_wide({ray}, {any}, {lane})",
        Layout::Wide,
        false,
        DepthRule::FinishOnHost(WIDE_STACK_GROUPS + 1)
    ),
];

/// The walk of `traversal`: the stackless walk is the short stack with a ring of none.
pub fn walk(traversal: Traversal) -> &'static Walk {
    match traversal {
        Traversal::FullStack => &WALKS[0],
        Traversal::Stackless | Traversal::ShortStack(_) => &WALKS[1],
        Traversal::Wide => &WALKS[2],
    }
}

/// The index of `traversal`'s walk in [`WALKS`].
pub fn index(traversal: Traversal) -> usize {
    let w = walk(traversal);
    WALKS.iter().position(|x| x == w).unwrap_or(0)
}

/// The ring of a short stack (`SHORT_STACK_SIZE`): 0 for the stackless walk, clamped to
/// `1..=MAX_SHORT_STACK` as the CPU walk clamps it, `None` for a walk without one.
pub fn short_stack_size(traversal: Traversal) -> Option<u32> {
    match traversal {
        Traversal::Stackless => Some(0),
        Traversal::ShortStack(k) => Some(k.clamp(1, MAX_SHORT_STACK)),
        Traversal::FullStack | Traversal::Wide => None,
    }
}

impl Walk {
    /// Its call with these arguments (`k`: a short stack's size, unread by the others).
    pub fn call_with(&self, ray: &str, any_hit: &str, k: &str, lane: &str) -> String {
        // The arguments hold no braces, so no placeholder is filled twice.
        self.call
            .replace("{ray}", ray)
            .replace("{any}", any_hit)
            .replace("{lane}", lane)
            .replace("{k}", k)
    }

    /// True for the wide layout's walk.
    pub fn is_wide(&self) -> bool {
        self.layout == Layout::Wide
    }
}

/// Checks that a binary tree `depth` levels deep can be walked with `traversal` by the
/// kernels ([`DepthRule::Refuse`]); the other walks take any depth.
pub fn check_depth(traversal: Traversal, depth: u32) -> Result<(), TraceError> {
    match walk(traversal).depth {
        DepthRule::Refuse(max) if depth > max => Err(TraceError::TooDeep { depth, max }),
        _ => Ok(()),
    }
}

/// True when a ray of `traversal`'s walk can overflow its stack on a tree of the walk's
/// layout `depth` levels deep, to be finished on the host ([`DepthRule::FinishOnHost`]).
pub fn may_overflow(traversal: Traversal, depth: u32) -> bool {
    matches!(walk(traversal).depth, DepthRule::FinishOnHost(max) if depth > max)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table and the CPU walks agree on what each walk reads, every traversal has a
    /// walk, and every entry point is named after its stem.
    #[test]
    fn the_table_agrees_with_the_cpu_walks() {
        for t in Traversal::ALL {
            let w = walk(t);
            assert_eq!(w.escapes, t.needs_escapes(), "{t}");
            assert_eq!(w.is_wide(), t.is_wide(), "{t}");
            assert!(w.call.starts_with(&format!("bvh_trace_{}(", w.stem)), "{t}");
            assert!(
                w.file.1.contains(&format!("fn bvh_trace_{}(", w.stem)),
                "{} defines bvh_trace_{}",
                w.file.0,
                w.stem
            );
        }
        assert_eq!(
            walk(Traversal::ShortStack(5)).call_with("r", "true", "5u", "l"),
            "bvh_trace_short_stack(r, true, 5u, l)"
        );
        assert!(check_depth(Traversal::FullStack, FULL_STACK_SIZE + 1).is_err());
        assert!(check_depth(Traversal::Stackless, 10_000).is_ok());
        assert!(may_overflow(Traversal::Wide, WIDE_STACK_GROUPS + 2));
        assert!(!may_overflow(Traversal::Wide, WIDE_STACK_GROUPS + 1));
        assert!(!may_overflow(Traversal::FullStack, 10_000));
    }
}
