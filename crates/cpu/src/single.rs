//! One ray at a time through the 4-wide layout: the four child boxes tested together, hit
//! children visited nearest first, popped children re-tested against the best hit, and a
//! leaf's triangles tested four at a time.

use bvhtrace_core::intersect::PreparedRay;
use bvhtrace_core::{Hit, INVALID_RAY, MISS, Ray};

use crate::lanes::Lanes;
use crate::layout::{CpuBvh, LEAF, Node4, leaf_range};
use crate::tests4::{RayLanes, box4, still_hit, tri4};

/// The best hit so far (the core walks' rule, see [`Best::offer`]).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Best {
    pub t: f32,
    pub prim: u32,
    pub u: f32,
    pub v: f32,
    pub found: bool,
}

impl Best {
    /// No hit yet: the interval ends at the ray's `t_max`.
    #[inline(always)]
    pub fn start(ray: &Ray) -> Best {
        Best {
            t: ray.t_max,
            prim: MISS,
            u: 0.0,
            v: 0.0,
            found: false,
        }
    }

    /// Takes the candidate when it is nearer, or as near with a lower primitive id: the
    /// rule of `bvhtrace_core::traverse`, which makes the closest hit independent of the
    /// order in which triangles are tested. True when it was taken.
    #[inline(always)]
    pub fn offer(&mut self, t: f32, prim: u32, u: f32, v: f32) -> bool {
        if t < self.t || (t == self.t && self.found && prim < self.prim) {
            *self = Best {
                t,
                prim,
                u,
                v,
                found: true,
            };
            true
        } else {
            false
        }
    }

    #[inline(always)]
    pub fn into_hit(self) -> Hit {
        if self.found {
            Hit {
                t: self.t,
                prim: self.prim,
                u: self.u,
                v: self.v,
            }
        } else {
            Hit::miss(self.t)
        }
    }
}

/// The hit of a ray that is not traced (as the core walks report it).
pub(crate) fn untraced(ray: &Ray) -> Hit {
    Hit {
        prim: INVALID_RAY,
        ..Hit::miss(if ray.t_max.is_nan() { 0.0 } else { ray.t_max })
    }
}

/// A child waiting on the stack: its reference, and what [`still_hit`] needs.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Entry {
    pub child: u32,
    pub tnear: f32,
    pub m: f32,
    pub far: f32,
}

/// Tests a leaf's blocks. Returns true when an any-hit query can stop.
#[inline(always)]
pub(crate) fn leaf<L: Lanes, const ANY: bool>(
    bvh: &CpuBvh,
    q: &RayLanes<L>,
    child: u32,
    best: &mut Best,
) -> bool {
    let (first, count) = leaf_range(child);
    for b in &bvh.blocks[first..first + count] {
        let (mut ok, t, u, v) = tri4(b, q);
        // Only lanes at or before the best can be taken; the rule settles the ties.
        ok &= t.le(L::splat(best.t)).bits();
        if ok == 0 {
            continue;
        }
        let (t, u, v) = (t.store(), u.store(), v.store());
        while ok != 0 {
            let i = ok.trailing_zeros() as usize;
            ok &= ok - 1;
            if best.offer(t[i], b.prim[i], u[i], v[i]) && ANY {
                return true;
            }
        }
    }
    false
}

/// Orders a node's hit children nearest first: pushes all but the nearest (farthest
/// first, so the nearer pop sooner) and returns the nearest.
#[inline(always)]
fn order<L: Lanes>(n: &Node4, mut hit: u32, lanes: (L, L, L), stack: &mut Vec<Entry>) -> u32 {
    if hit & (hit - 1) == 0 {
        return n.child[hit.trailing_zeros() as usize];
    }
    // Only a node with two or more hit children needs the distances.
    let (tnear, m, far) = (lanes.0.store(), lanes.1.store(), lanes.2.store());
    let entry = |i: usize| Entry {
        child: n.child[i],
        tnear: tnear[i],
        m: m[i],
        far: far[i],
    };
    let a = hit.trailing_zeros() as usize;
    hit &= hit - 1;
    let b = hit.trailing_zeros() as usize;
    hit &= hit - 1;
    if hit == 0 {
        let (near, far_one) = if tnear[b] < tnear[a] { (b, a) } else { (a, b) };
        stack.push(entry(far_one));
        return n.child[near];
    }
    // Three or four: a small insertion sort by entry distance, farthest first.
    let mut lanes = [a, b, 0, 0];
    let mut len = 2;
    while hit != 0 {
        lanes[len] = hit.trailing_zeros() as usize;
        hit &= hit - 1;
        len += 1;
    }
    for i in 1..len {
        let mut j = i;
        while j > 0 && tnear[lanes[j - 1]] < tnear[lanes[j]] {
            lanes.swap(j - 1, j);
            j -= 1;
        }
    }
    for &l in &lanes[..len - 1] {
        stack.push(entry(l));
    }
    n.child[lanes[len - 1]]
}

/// One ray's walk (closest hit, or any hit with `ANY`), with a stack reused across rays.
#[inline(always)]
pub(crate) fn trace<L: Lanes, const ANY: bool>(
    bvh: &CpuBvh,
    ray: &Ray,
    stack: &mut Vec<Entry>,
) -> Hit {
    if !ray.is_valid() {
        return untraced(ray);
    }
    let mut best = Best::start(ray);
    if bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
        return best.into_hit();
    }
    let r = PreparedRay::new(ray);
    let q = RayLanes::<L>::new(r);
    stack.clear();
    let mut child = 0u32;
    loop {
        if child & LEAF == 0 {
            let n = &bvh.nodes[child as usize];
            let (hit, tnear, m, far) = box4(n, &q, best.t);
            if hit != 0 {
                child = order(n, hit, (tnear, m, far), stack);
                continue;
            }
        } else if leaf::<L, ANY>(bvh, &q, child, &mut best) {
            return best.into_hit();
        }
        // Pop the next child still hit against the best so far.
        loop {
            let Some(e) = stack.pop() else {
                return best.into_hit();
            };
            if ANY || !best.found || still_hit(&r, e.tnear, e.m, e.far, best.t) {
                child = e.child;
                break;
            }
        }
    }
}
