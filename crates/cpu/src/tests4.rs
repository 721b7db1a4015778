//! The box tests over eight lanes (a node's children) and the triangle tests over four (a
//! block's triangles), lane for lane the f32 operations of
//! `bvhtrace_core::intersect::{intersect_box, intersect_triangle}` in the same order, and
//! the ray preparation they share.

use bvhtrace_core::Ray;
use bvhtrace_core::intersect::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG};

use crate::lanes::{Lanes, Wide};
use crate::layout::{Node8, Tri4, WIDTH};

/// A ray prepared for the tests: what `PreparedRay::new` computes, to the bit, built
/// without its per-axis indexing, and splatted once per ray into the box test's eight
/// lanes `W` (and the triangle test's four `L`). What only the
/// triangle test needs is [`ShearLanes`], made at the ray's first leaf (most primary rays
/// reach none).
#[derive(Clone, Copy)]
pub(crate) struct RayLanes<L, W> {
    pub org: [W; 3],
    /// `-1 / dir` (with `safe_inverse`'s zero handling): `(o - p) * -inv` is
    /// `(p - o) * inv` to the bit but for the sign of a zero, and lets the plane be a
    /// memory operand of the subtraction.
    pub ninv: [W; 3],
    pub t_min: W,
    pub t_max: W,
    /// `t_min` for the triangle test.
    pub t_min4: L,
    /// The watertight test's dominant axis (`PreparedRay::kz`).
    pub kz: usize,
    /// Some direction component is zero (after the flush of subnormals).
    pub parallel: bool,
    /// The direction with subnormal components flushed (`PreparedRay::dir`).
    pub dir: [f32; 3],
    /// The interval's end (`Ray::t_max`).
    pub t_max_s: f32,
    /// `t_min` as one value.
    pub t_min_s: f32,
}

/// Up to [`RAYS`] rays prepared together, ray `i` in lane `i`: `Ray::is_valid` and the
/// values of `PreparedRay::new` the walks need, bit for bit, eight rays per operation
/// (the per-ray preparation was most of a primary ray's instructions, since most primary
/// rays test one or two nodes).
pub(crate) struct Prepared {
    /// The origins, `org[axis][ray]`.
    pub org: [[f32; RAYS]; 3],
    /// `-1 / dir` with `safe_inverse`'s zero handling (see [`RayLanes::ninv`]).
    pub ninv: [[f32; RAYS]; 3],
    /// The directions with subnormal components flushed (`PreparedRay::dir`).
    pub dir: [[f32; RAYS]; 3],
    /// The dominant axes (`PreparedRay::kz`).
    pub kz: [usize; RAYS],
    /// Bit `i`: ray `i` is present and valid.
    pub valid: u32,
    /// Bit `i`: ray `i` has a zero component (`PreparedRay::parallel`).
    pub parallel: u32,
    /// The shear constants `sx`, `sy`, `sz`: `shear[k][ray]`.
    pub shear: [[f32; RAYS]; 3],
    /// Bit `i`: ray `i`'s `kx` and `ky` are swapped (`dir[kz] < 0`).
    pub swap: u32,
    /// The intervals' ends, `Ray::t_min` and `Ray::t_max`.
    pub t_min: [f32; RAYS],
    pub t_max: [f32; RAYS],
}

/// Rays prepared together by [`Prepared::new`]: one per lane of [`Wide`].
pub(crate) const RAYS: usize = 8;

/// A box around every box of a tree's root node, plane by plane (`lo`, `hi` per axis):
/// a ray whose box test misses it misses every box inside it, so it needs no walk (see
/// [`Prepared::may_enter`]).
#[derive(Clone, Copy, Debug)]
pub(crate) struct SceneBox {
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}

impl SceneBox {
    /// The smallest box around both planes of every used slot of `root`, on each axis;
    /// `None` when a plane is NaN (no such box) or no slot is used.
    pub fn around(root: &Node8) -> Option<SceneBox> {
        if root.used == 0 {
            return None;
        }
        let mut b = SceneBox {
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
        };
        for i in (0..WIDTH).filter(|&i| root.used >> i & 1 != 0) {
            for a in 0..3 {
                let (p, q) = (root.planes[2 * a][i], root.planes[2 * a + 1][i]);
                if p.is_nan() || q.is_nan() {
                    return None;
                }
                b.lo[a] = b.lo[a].min(p.min(q));
                b.hi[a] = b.hi[a].max(p.max(q));
            }
        }
        Some(b)
    }
}

/// The triangle test's axes `[kx, ky, kz]` for the dominant axis `kz` (`shear_axes`): the
/// next two axes in turn, swapped when `swap` (`dir[kz] < 0`) to keep the winding.
#[inline(always)]
pub(crate) fn sheared_axes(kz: usize, swap: bool) -> [usize; 3] {
    // `(kz + 1) % 3` and `(kz + 2) % 3` without a division.
    const NEXT: [[usize; 2]; 3] = [[1, 2], [2, 0], [0, 1]];
    let [kx, ky] = NEXT[kz];
    if swap { [ky, kx, kz] } else { [kx, ky, kz] }
}

/// The triangle test's shear of eight rays from their directions `dir` (flushed):
/// `shear_axes`' dominant axis per lane (0.0, 1.0 or 2.0), the rays whose `kx` and `ky`
/// swap (`dir[kz] < 0`, as bits), and `PreparedRay::new`'s `sx`, `sy`, `sz`.
#[inline(always)]
pub(crate) fn shear_lanes<W: Wide>(dir: [W; 3]) -> (W, u32, [W; 3]) {
    let zero = W::splat(0.0);
    let abs = [dir[0].abs(), dir[1].abs(), dir[2].abs()];
    // `shear_axes`: the first of the largest magnitudes.
    let x_max = abs[0].ge(abs[1]).and(abs[0].ge(abs[2]));
    let y_over_z = abs[1].ge(abs[2]);
    // Per lane the component on axis `kz`, `(kz + 1) % 3` and `(kz + 2) % 3`.
    let pick = |a: W, b: W, c: W| x_max.select(a, y_over_z.select(b, c));
    let dkz = pick(dir[0], dir[1], dir[2]);
    let (d1, d2) = (pick(dir[1], dir[2], dir[0]), pick(dir[2], dir[0], dir[1]));
    let swap = dkz.lt(zero);
    let (dkx, dky) = (swap.select(d2, d1), swap.select(d1, d2));
    let shear = [dkx.div(dkz), dky.div(dkz), W::splat(1.0).div(dkz)];
    let kz = pick(zero, W::splat(1.0), W::splat(2.0));
    (kz, swap.bits(), shear)
}

/// Three lanes' values.
#[inline(always)]
fn store3<W: Wide>(v: [W; 3]) -> [[f32; RAYS]; 3] {
    [v[0].store(), v[1].store(), v[2].store()]
}

/// A ray's eight f32 fields (origin, `t_min`, direction, `t_max`) as one row.
#[inline(always)]
pub(crate) fn row(r: &Ray) -> &[f32; 8] {
    const { assert!(size_of::<Ray>() == size_of::<[f32; 8]>()) };
    // SAFETY: `Ray` is `repr(C)` with eight f32 fields and no padding (size checked
    // above), so it has the layout of `[f32; 8]` (whose alignment is f32's).
    unsafe { &*(r as *const Ray).cast::<[f32; 8]>() }
}

impl Prepared {
    /// Ray `i` (its interval `t_min..t_max`) as the core's `PreparedRay`, for its scalar box test: the
    /// same origin, direction, inverse (`1 / d` is `-(-1 / d)` exactly), interval and axes.
    #[inline(always)]
    pub fn core_ray(
        &self,
        i: usize,
        t_min: f32,
        t_max: f32,
    ) -> bvhtrace_core::intersect::PreparedRay {
        let [kx, ky, kz] = sheared_axes(self.kz[i], self.swap >> i & 1 != 0);
        let v = |a: [[f32; RAYS]; 3]| glam::Vec3::new(a[0][i], a[1][i], a[2][i]);
        bvhtrace_core::intersect::PreparedRay {
            org: v(self.org),
            dir: v(self.dir),
            inv_dir: -v(self.ninv),
            parallel: self.parallel >> i & 1 != 0,
            t_min,
            t_max,
            kx,
            ky,
            kz,
            sx: self.shear[0][i],
            sy: self.shear[1][i],
            sz: self.shear[2][i],
        }
    }

    /// Prepares one to [`RAYS`] rays, loaded by one transpose of their rows.
    #[inline(always)]
    pub fn new<W: Wide>(rays: &[Ray]) -> Prepared {
        let mut p = Self::for_boxes::<W>(rays);
        p.shear::<W>();
        p
    }

    /// [`Prepared::new`] without the triangle test's shear (`kz`, `shear` and `swap`
    /// are left zero until [`Prepared::shear`]): what the box tests and the validity
    /// need.
    #[inline(always)]
    pub fn for_boxes<W: Wide>(rays: &[Ray]) -> Prepared {
        debug_assert!((1..=RAYS).contains(&rays.len()));
        // Missing lanes repeat the last ray; they are not valid. No `array::map` over
        // AVX lanes here: its closure would be compiled apart from an AVX2 caller.
        let last = rays.len() - 1;
        let at = |j: usize| row(&rays[if j < last { j } else { last }]);
        let r = [at(0), at(1), at(2), at(3), at(4), at(5), at(6), at(7)];
        let [ox, oy, oz, t_min, dx, dy, dz, t_max] = W::columns(r);
        let (o, d) = ([ox, oy, oz], [dx, dy, dz]);
        let (inf, zero) = (W::splat(f32::INFINITY), W::splat(0.0));
        // `|x| < inf` is false for an infinity and for NaN; `x == x` only for NaN.
        let mut ok = t_min.eq(t_min).and(t_max.eq(t_max));
        for a in 0..3 {
            ok = ok.and(o[a].abs().lt(inf)).and(d[a].abs().lt(inf));
        }
        let zero_dir = d[0].eq(zero).and(d[1].eq(zero)).and(d[2].eq(zero)).bits();
        let present = (2u32 << last) - 1;
        let (mut dir, mut ninv) = ([zero; 3], [zero; 3]);
        for a in 0..3 {
            // `flush_subnormal` and `safe_inverse` as lane selects.
            let sign = d[a].and(W::splat(-0.0));
            let small = d[a].abs().lt(W::splat(f32::MIN_POSITIVE));
            dir[a] = small.select(sign, d[a]);
            let safe = small.select(sign.or(W::splat(f32::MIN_POSITIVE)), d[a]);
            ninv[a] = W::splat(-1.0).div(safe);
        }
        let parallel = dir[0].eq(zero).or(dir[1].eq(zero)).or(dir[2].eq(zero));
        Prepared {
            org: store3(o),
            ninv: store3(ninv),
            dir: store3(dir),
            kz: [0; RAYS],
            valid: ok.bits() & !zero_dir & present,
            parallel: parallel.bits(),
            shear: [[0.0; RAYS]; 3],
            swap: 0,
            t_min: t_min.store(),
            t_max: t_max.store(),
        }
    }

    /// The triangle test's shear of the rays (`shear_axes` and the shear constants of
    /// `PreparedRay::new`), from their flushed directions.
    #[inline(always)]
    pub fn shear<W: Wide>(&mut self) {
        let dir = [
            W::load(&self.dir[0]),
            W::load(&self.dir[1]),
            W::load(&self.dir[2]),
        ];
        let (kz, swap, shear) = shear_lanes(dir);
        let (x, y) = (kz.eq(W::splat(0.0)).bits(), kz.eq(W::splat(1.0)).bits());
        self.kz = std::array::from_fn(|i| {
            if x >> i & 1 != 0 {
                0
            } else if y >> i & 1 != 0 {
                1
            } else {
                2
            }
        });
        self.shear = store3(shear);
        self.swap = swap;
    }

    /// The rays (bits) whose walk may hit something inside `b` (every ray when the tree
    /// has no such box, see [`SceneBox::around`]): those whose box test
    /// against `b` hits, and those along a slab. The test is [`box8`]'s signed one, whose
    /// every step is monotone (f32 subtraction and multiplication in each operand, `min`,
    /// `max`, the exit scale); a box inside `b` has both planes of each axis between
    /// `b`'s, so its entry is at or after `b`'s and its exit at or before: when the ray
    /// misses `b`, it misses every box of the root node, and the walk finds nothing.
    #[inline(always)]
    pub fn may_enter<W: Wide>(&self, b: Option<&SceneBox>) -> u32 {
        let Some(b) = b else {
            return u32::MAX;
        };
        let (mut near, mut far) = (W::load(&self.t_min), W::load(&self.t_max));
        for a in 0..3 {
            let (o, n) = (W::load(&self.org[a]), W::load(&self.ninv[a]));
            let t0 = o.sub(W::splat(b.lo[a])).mul(n);
            let t1 = o.sub(W::splat(b.hi[a])).mul(n);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        let scale = far
            .lt(W::splat(0.0))
            .select(W::splat(BOX_TFAR_SCALE_NEG), W::splat(BOX_TFAR_SCALE));
        near.le(far.mul(scale)).bits() | self.parallel
    }
}

impl<L: Lanes, W: Wide> RayLanes<L, W> {
    /// Ray `i` of `p` (`ray` itself), splatted.
    #[inline(always)]
    pub fn from_prepared(p: &Prepared, ray: &Ray, i: usize) -> Self {
        RayLanes {
            // No closures over AVX lanes here or in the box test: a closure is compiled
            // apart from the AVX2 caller, and its AVX operations would not be inlined.
            org: [
                W::splat(p.org[0][i]),
                W::splat(p.org[1][i]),
                W::splat(p.org[2][i]),
            ],
            ninv: [
                W::splat(p.ninv[0][i]),
                W::splat(p.ninv[1][i]),
                W::splat(p.ninv[2][i]),
            ],
            t_min: W::splat(ray.t_min),
            t_max: W::splat(ray.t_max),
            t_min4: L::splat(ray.t_min),
            kz: p.kz[i],
            parallel: p.parallel >> i & 1 != 0,
            dir: [p.dir[0][i], p.dir[1][i], p.dir[2][i]],
            t_max_s: ray.t_max,
            t_min_s: ray.t_min,
        }
    }

    /// One valid ray, prepared alone.
    #[cfg(test)]
    pub fn prepare(ray: &Ray) -> Self {
        let p = Prepared::new::<W>(std::slice::from_ref(ray));
        assert!(p.valid & 1 != 0, "{ray:?} is not valid");
        Self::from_prepared(&p, ray, 0)
    }
}

/// The triangle test's shear (`PreparedRay::kx`, `ky`, `kz`, `sx`, `sy`, `sz`), bit for
/// bit, and the origin in the sheared axes' order, so that the test reads the lanes it
/// needs without indexing.
#[derive(Clone, Copy)]
pub(crate) struct ShearLanes<L> {
    pub kx: usize,
    pub ky: usize,
    pub kz: usize,
    /// `sx`, `sy`, `sz`.
    pub s: [L; 3],
    /// The origin's `kx`, `ky` and `kz` coordinates.
    pub o: [L; 3],
}

impl<L: Lanes> ShearLanes<L> {
    /// The shear of ray `i` of `p`, whose dominant axis is `kz` (`p.kz[i]`).
    #[inline(always)]
    pub fn from_prepared(p: &Prepared, i: usize, kz: usize) -> Self {
        let [kx, ky, kz] = sheared_axes(kz, p.swap >> i & 1 != 0);
        ShearLanes {
            kx,
            ky,
            kz,
            s: [0, 1, 2].map(|k| L::splat(p.shear[k][i])),
            o: [kx, ky, kz].map(|a| L::splat(p.org[a][i])),
        }
    }

    /// One valid ray's shear, prepared alone.
    #[cfg(test)]
    pub fn prepare(ray: &Ray) -> Self {
        let p = Prepared::new::<crate::lanes::Pair<L>>(std::slice::from_ref(ray));
        Self::from_prepared(&p, 0, p.kz[0])
    }
}

/// A node's eight box tests: the hit slots (used ones only), and per lane what the walk
/// keeps of a hit child (see [`BoxHits`]). Per axis the scalar test's `fmin(t0, t1)` and
/// `fmax(t0, t1)`, each `t` negated exactly (see [`RayLanes::ninv`]); no NaN arises off
/// the parallel path, and the sign of a zero reaches no comparison.
///
/// `OCT` is [`MINMAX`], or the ray's [`octant`] (then `KZ` is not read, and neither is the
/// culling slack's `m`: only any-hit walks, which never cull, take it).
///
/// `PARALLEL` and `KZ` are the ray's `parallel` and `kz`, fixed per walk so that the
/// dominant axis's lanes stay in registers, or `KZ` is [`RUN_AXIS`].
///
/// `culled` says the best hit `t_best` may lie before the ray's `t_max`; without it the
/// culling slack is left out, since `fmin(t_max + slack, t_max)` is `t_max` (the slack
/// is never negative). `SIGNED` is false for rays with `t_min >= 0`: every hit box's
/// entry is then at or after 0, so a negative exit fails the test whichever scale it
/// takes (neither scale takes it to zero: both are above one half), and the positive
/// scale serves every lane.
#[inline(always)]
pub(crate) fn box8<
    L: Lanes,
    W: Wide,
    const SIGNED: bool,
    const PARALLEL: bool,
    const KZ: usize,
    const OCT: usize,
>(
    n: &Node8,
    q: &RayLanes<L, W>,
    t_best: f32,
    culled: bool,
) -> BoxHits<W> {
    debug_assert!(PARALLEL == q.parallel && (OCT != MINMAX || KZ == q.kz || KZ == RUN_AXIS));
    let (near, far) = if PARALLEL {
        parallel_slabs(n, q)
    } else if OCT != MINMAX {
        debug_assert_eq!(OCT, octant(q.dir));
        // The plane the ray enters a slab by gives the smaller distance (`(o - p) * -inv`
        // is monotone in `p`, and the conversion keeps every lower plane at or below its
        // upper one): `fmin(t0, t1)` and `fmax(t0, t1)` without either, but for the sign
        // of a zero.
        let (mut near, mut far) = ([W::splat(0.0); 3], [W::splat(0.0); 3]);
        for a in 0..3 {
            let back = OCT >> a & 1;
            near[a] = q.org[a]
                .sub(W::load(&n.planes[2 * a + back]))
                .mul(q.ninv[a]);
            far[a] = q.org[a]
                .sub(W::load(&n.planes[2 * a + 1 - back]))
                .mul(q.ninv[a]);
        }
        (near, far)
    } else {
        let (mut near, mut far) = ([W::splat(0.0); 3], [W::splat(0.0); 3]);
        for a in 0..3 {
            let t0 = q.org[a].sub(W::load(&n.planes[2 * a])).mul(q.ninv[a]);
            let t1 = q.org[a].sub(W::load(&n.planes[2 * a + 1])).mul(q.ninv[a]);
            near[a] = t0.min(t1);
            far[a] = t0.max(t1);
        }
        (near, far)
    };
    let tnear = near[0].max(near[1]).max(near[2].max(q.t_min));
    let (near_kz, far_kz) = if KZ == RUN_AXIS {
        (near[q.kz], far[q.kz])
    } else {
        (near[KZ], far[KZ])
    };
    let slabs = far[0].min(far[1]).min(far[2]);
    let tfar = if culled {
        let m = near_kz.abs().max(far_kz.abs());
        let limit = W::splat(t_best)
            .add(W::splat(BOX_CULL_SLACK).mul(m))
            .min(q.t_max);
        far[0].min(far[1]).min(far[2].min(limit))
    } else {
        // The same minimum in another order: no NaN reaches it, and the sign of a zero
        // is not seen by the comparison.
        slabs.min(q.t_max)
    };
    let scale = if SIGNED {
        tfar.lt(W::splat(0.0))
            .select(W::splat(BOX_TFAR_SCALE_NEG), W::splat(BOX_TFAR_SCALE))
    } else {
        W::splat(BOX_TFAR_SCALE)
    };
    BoxHits {
        hit: tnear.le(tfar.mul(scale)).bits() & n.used,
        tnear,
        far: slabs,
        near_kz,
        far_kz,
    }
}

/// [`box8`]'s `OCT` for the per-axis `fmin` and `fmax` (any ray).
pub(crate) const MINMAX: usize = 8;

/// [`box8`]'s `KZ` for a dominant axis read from the ray at run time (a stream's rays,
/// of one octant but any axis).
pub(crate) const RUN_AXIS: usize = 3;

/// The octant of direction `dir` (no zero component): bit `a` set when it goes down axis
/// `a`. [`box8`] with it as `OCT` reads each slab's entry from one plane.
#[inline(always)]
pub(crate) fn octant(dir: [f32; 3]) -> usize {
    usize::from(dir[0] < 0.0) | usize::from(dir[1] < 0.0) << 1 | usize::from(dir[2] < 0.0) << 2
}

/// What [`box8`] found: the hit slots, and per lane the entry distance, the slabs' exit
/// before the interval's end is applied, and the two distances on the dominant axis
/// (whose magnitudes bound the culling slack): what [`still_hit`] re-tests with.
#[derive(Clone, Copy)]
pub(crate) struct BoxHits<W> {
    pub hit: u32,
    pub tnear: W,
    pub far: W,
    near_kz: W,
    far_kz: W,
}

impl<W: Wide> BoxHits<W> {
    /// The culling slack's magnitude `m` per lane (`intersect_box`'s `m`): only a node
    /// with two hit children or more needs it, for the children it pushes.
    #[inline(always)]
    pub fn m(&self) -> W {
        self.near_kz.abs().max(self.far_kz.abs())
    }
}

/// The per-axis `fmin(t0, t1)` and `fmax(t0, t1)` of the scalar test's general path, for
/// rays along some slab: inside the slab for every t, or for none. Inlined (into the
/// walks for such rays only), so that the ray's lanes need not be kept in memory.
#[inline(always)]
fn parallel_slabs<L: Lanes, W: Wide>(n: &Node8, q: &RayLanes<L, W>) -> ([W; 3], [W; 3]) {
    let mut near = [W::splat(0.0); 3];
    let mut far = near;
    for a in 0..3 {
        let (lo, hi) = (W::load(&n.planes[2 * a]), W::load(&n.planes[2 * a + 1]));
        let (mut t0, mut t1) = (
            q.org[a].sub(lo).mul(q.ninv[a]),
            q.org[a].sub(hi).mul(q.ninv[a]),
        );
        if q.dir[a] == 0.0 {
            let o = q.org[a];
            let inside = lo.le(o).and(o.le(hi));
            t0 = inside.select(W::splat(f32::NEG_INFINITY), W::splat(f32::INFINITY));
            t1 = W::splat(f32::INFINITY);
        }
        near[a] = t0.min(t1);
        far[a] = t0.max(t1);
    }
    (near, far)
}

/// The box test of a child [`box8`] hit, repeated against a nearer best hit from its
/// entry distance, slack magnitude and slab exit: the same answer as the full test
/// (`min` over finite values is associative, and a signed zero compares as zero).
#[inline(always)]
pub(crate) fn still_hit(t_max: f32, tnear: f32, m: f32, far: f32, t_best: f32) -> bool {
    let fmin = |a: f32, b: f32| if a < b { a } else { b };
    let limit = fmin(t_best + BOX_CULL_SLACK * m, t_max);
    let tfar = fmin(far, limit);
    let tfar = tfar
        * if tfar < 0.0 {
            BOX_TFAR_SCALE_NEG
        } else {
            BOX_TFAR_SCALE
        };
    tnear <= tfar
}

/// The scalar box test of slot `i` of `n` (what [`box8`]'s lane `i` must equal).
#[cfg(test)]
pub(crate) fn box_lane(
    n: &Node8,
    r: &bvhtrace_core::intersect::PreparedRay,
    i: usize,
    t_best: f32,
) -> bool {
    let b = n.child_box(i);
    let (lo, hi) = (b.min, b.max);
    bvhtrace_core::intersect::intersect_box(r, lo, hi, t_best).is_some()
}

/// `p.x q.y - p.y q.x`: [`edge`] up to the sign of a zero.
#[inline(always)]
fn edge_fast<L: Lanes>(px: L, py: L, qx: L, qy: L) -> L {
    px.mul(qy).sub(py.mul(qx))
}

/// The edge function of `intersect::edge` over lanes: the corners taken in one fixed
/// order, the sign restored (`-(q.x p.y - q.y p.x)` is not `p.x q.y - p.y q.x` for a zero).
#[inline(always)]
fn edge<L: Lanes>(px: L, py: L, qx: L, qy: L) -> L {
    let swap = px.gt(qx).or(px.eq(qx).and(py.gt(qy)));
    let (pq, qp) = (px.mul(qy), py.mul(qx));
    swap.select(qp.sub(pq).neg(), pq.sub(qp))
}

/// The watertight test on a block's four triangles (`t_min` the ray's, splatted): the
/// lanes that hit at `t >= t_min`, and per lane `t` and the weights of corners 1 and 2
/// (unspecified where no lane hits). `ANY`: for an any-hit walk.
#[inline(always)]
pub(crate) fn tri4<L: Lanes, const ANY: bool>(
    b: &Tri4,
    t_min: L,
    s: &ShearLanes<L>,
) -> (u32, L, L, L) {
    let (kx, ky, kz) = (s.kx, s.ky, s.kz);
    let [sx, sy, sz] = s.s;
    let [ox, oy, oz] = s.o;
    let rel = |c: usize, a: usize, o: L| L::load(&b.v[c][a]).sub(o);
    let (az, bz, cz) = (rel(0, kz, oz), rel(1, kz, oz), rel(2, kz, oz));
    let ax = rel(0, kx, ox).sub(sx.mul(az));
    let ay = rel(0, ky, oy).sub(sy.mul(az));
    let bx = rel(1, kx, ox).sub(sx.mul(bz));
    let by = rel(1, ky, oy).sub(sy.mul(bz));
    let cx = rel(2, kx, ox).sub(sx.mul(cz));
    let cy = rel(2, ky, oy).sub(sy.mul(cz));
    // The edge functions up to the sign of a zero first: comparisons with zero do not
    // see it, and it reaches `det`, `t` or the weights only through a zero edge function
    // of a lane that passes the mixed-sign test, where the exact ones are computed.
    let mut u = edge_fast(cx, cy, bx, by);
    let mut v = edge_fast(ax, ay, cx, cy);
    let mut w = edge_fast(bx, by, ax, ay);
    let zero = L::splat(0.0);
    let negative = u.lt(zero).or(v.lt(zero)).or(w.lt(zero));
    let positive = u.gt(zero).or(v.gt(zero)).or(w.gt(zero));
    let inside = !negative.and(positive).bits() & 0b1111;
    // Most blocks a primary ray reaches it misses: no distance to compute. A shadow ray's
    // first blocks pass the edge tests on the triangle it leaves, so the branch would
    // often mispredict: an any-hit walk computes every lane.
    if !ANY && inside == 0 {
        return (0, zero, zero, zero);
    }
    if u.eq(zero).or(v.eq(zero)).or(w.eq(zero)).bits() & inside != 0 {
        u = edge(cx, cy, bx, by);
        v = edge(ax, ay, cx, cy);
        w = edge(bx, by, ax, ay);
    }
    // A lane with `det == 0` is left out (its `t` may be NaN).
    let det = u.add(v).add(w);
    let inside = inside & !det.eq(zero).bits();
    let t_scaled = u
        .mul(sz.mul(az))
        .add(v.mul(sz.mul(bz)))
        .add(w.mul(sz.mul(cz)));
    let inv_det = L::splat(1.0).div(det);
    let t = t_scaled.mul(inv_det);
    let ok = t.ge(t_min).bits() & inside;
    (ok, t, v.mul(inv_det), w.mul(inv_det))
}

/// A ray as a leaf's hits near an end of its interval need it (see [`near_ends`]): for
/// the binary walk's box test of their leaves, which is rare enough to prepare the ray
/// again for it.
#[derive(Clone, Copy)]
pub(crate) enum RayAt<'a> {
    /// Ray `i` of a prepared group, with its interval.
    Lanes {
        p: &'a Prepared,
        i: usize,
        t_min: f32,
        t_max: f32,
    },
    /// The ray itself.
    Ray(&'a Ray),
}

impl RayAt<'_> {
    /// The end of the interval.
    #[inline(always)]
    pub fn t_max(&self) -> f32 {
        match self {
            RayAt::Lanes { t_max, .. } => *t_max,
            RayAt::Ray(r) => r.t_max,
        }
    }

    /// True when a hit at `t` on lane `i` of block `b` may lie outside the interval
    /// ([`near_end`]); always true for a ray not prepared in lanes.
    #[inline(always)]
    pub fn near_end(&self, t: f32, b: &Tri4, i: usize) -> bool {
        match *self {
            RayAt::Lanes {
                p,
                i: r,
                t_min,
                t_max,
            } => {
                let kz = p.kz[r];
                let zs = [b.v[0][kz][i], b.v[1][kz][i], b.v[2][kz][i]];
                near_end(t, t_min, t_max, zs, p.org[kz][r], p.shear[2][r])
            }
            RayAt::Ray(_) => true,
        }
    }

    /// The ray as the core's `PreparedRay`.
    #[inline(always)]
    pub fn prepared(&self) -> bvhtrace_core::intersect::PreparedRay {
        match *self {
            RayAt::Lanes { p, i, t_min, t_max } => p.core_ray(i, t_min, t_max),
            RayAt::Ray(r) => bvhtrace_core::intersect::PreparedRay::new(r),
        }
    }
}

/// True when a hit at `t` on a triangle whose corners lie at `zs` along the ray's dominant
/// axis (origin `oz`, scale `sz`) is within `NEAR_END` of an end of the interval: what
/// [`near_ends`] computes per lane, for one ray.
#[inline(always)]
pub(crate) fn near_end(t: f32, t_min: f32, t_max: f32, zs: [f32; 3], oz: f32, sz: f32) -> bool {
    let z = |c: usize| (zs[c] - oz).abs();
    let e = z(0).max(z(1)).max(z(2)) * sz.abs() * NEAR_END;
    t - t_min < e || t_max - t < e
}

/// The lanes of `t` (a block's hits) within `2^-16 m` of the interval's ends, `m` the
/// largest distance of a triangle's corners along the dominant axis: where f32 puts a
/// triangle's `t` at most `2^-18 m` from its exact distance (see `BOX_CULL_SLACK`), so
/// only there can the triangle lie outside the interval while its `t` lies inside it. Only
/// those hits need their leaf's box tested (see [`crate::layout::LeafBoxes`]).
#[inline(always)]
pub(crate) fn near_ends<L: Lanes>(b: &Tri4, s: &ShearLanes<L>, t: L, t_min: L, t_max: f32) -> u32 {
    let oz = s.o[2];
    let z = |c: usize| L::load(&b.v[c][s.kz]).sub(oz).abs();
    let e = z(0)
        .max(z(1))
        .max(z(2))
        .mul(s.s[2].abs())
        .mul(L::splat(NEAR_END));
    (t.sub(t_min).lt(e).or(L::splat(t_max).sub(t).lt(e))).bits()
}

/// `2^-16`: four times `BOX_CULL_SLACK`, a margin over the bound it stands for.
const NEAR_END: f32 = 1.0 / 65536.0;

#[cfg(test)]
pub(crate) mod tests {
    use bvhtrace_core::intersect::{PreparedRay, intersect_triangle};
    use bvhtrace_core::{Aabb, Ray};
    use glam::Vec3;

    use super::{
        BoxHits, MINMAX, Prepared, RayLanes, SceneBox, ShearLanes, box_lane, box8, octant,
        still_hit, tri4,
    };
    use crate::lanes::{Lanes, Pair, Portable, Wide};
    use crate::layout::{Node8, Tri4};

    /// The portable lanes, four and eight.
    type PortableRay = RayLanes<Portable, Pair<Portable>>;
    /// The SSE lanes, four and eight.
    #[cfg(target_arch = "x86_64")]
    type SseRay = RayLanes<crate::lanes::Sse, Pair<crate::lanes::Sse>>;
    /// The SSE lanes for triangles, AVX for boxes (run only where the CPU has AVX2).
    #[cfg(target_arch = "x86_64")]
    type AvxRay = RayLanes<crate::lanes::Sse, crate::lanes::Avx8>;

    #[cfg(target_arch = "x86_64")]
    fn has_avx2() -> bool {
        std::arch::is_x86_feature_detected!("avx2")
    }

    pub(crate) fn next(s: &mut u64) -> f32 {
        *s ^= *s << 13;
        *s ^= *s >> 7;
        *s ^= *s << 17;
        (*s >> 40) as f32 / (1u64 << 24) as f32
    }

    /// A value from several regimes: ordinary, tiny, huge, exact small ones and zeros.
    pub(crate) fn value(s: &mut u64) -> f32 {
        let x = next(s) * 2.0 - 1.0;
        match (next(s) * 6.0) as u32 {
            0 => x * 1e-3,
            1 => x * 1e6,
            2 => 0.0,
            3 => (x * 4.0).round() * 0.5,
            _ => x * 10.0,
        }
    }

    pub(crate) fn point(s: &mut u64) -> Vec3 {
        Vec3::new(value(s), value(s), value(s))
    }

    pub(crate) fn ray(s: &mut u64) -> Ray {
        let mut d = point(s);
        // Axis-parallel with signed zeros, and subnormal components, now and then.
        match (next(s) * 5.0) as u32 {
            0 => d = Vec3::new(-0.0, if next(s) < 0.5 { 1.0 } else { -1.0 }, 0.0),
            1 => d.x = 1e-40,
            _ => {}
        }
        if d == Vec3::ZERO {
            d = Vec3::Z;
        }
        let t_min = if next(s) < 0.2 { -value(s).abs() } else { 0.0 };
        let t_max = if next(s) < 0.3 {
            value(s).abs()
        } else {
            f32::INFINITY
        };
        Ray::with_interval(point(s), d, t_min, t_max)
    }

    /// [`box8`] for the ray's own `parallel` and `kz`.
    fn box8_dyn<L: Lanes, W: Wide, const SIGNED: bool>(
        n: &Node8,
        q: &RayLanes<L, W>,
        t_best: f32,
        culled: bool,
    ) -> BoxHits<W> {
        const M: usize = MINMAX;
        match (q.parallel, q.kz) {
            (false, 0) => box8::<L, W, SIGNED, false, 0, M>(n, q, t_best, culled),
            (false, 1) => box8::<L, W, SIGNED, false, 1, M>(n, q, t_best, culled),
            (false, _) => box8::<L, W, SIGNED, false, 2, M>(n, q, t_best, culled),
            (true, 0) => box8::<L, W, SIGNED, true, 0, M>(n, q, t_best, culled),
            (true, 1) => box8::<L, W, SIGNED, true, 1, M>(n, q, t_best, culled),
            (true, _) => box8::<L, W, SIGNED, true, 2, M>(n, q, t_best, culled),
        }
    }

    /// [`box8`] for the octant of a ray not along a slab (without the culling slack, as
    /// the any-hit walks run it).
    fn box8_octant<L: Lanes, W: Wide, const SIGNED: bool>(
        n: &Node8,
        q: &RayLanes<L, W>,
        t_best: f32,
    ) -> BoxHits<W> {
        match octant(q.dir) {
            0 => box8::<L, W, SIGNED, false, 0, 0>(n, q, t_best, false),
            1 => box8::<L, W, SIGNED, false, 0, 1>(n, q, t_best, false),
            2 => box8::<L, W, SIGNED, false, 0, 2>(n, q, t_best, false),
            3 => box8::<L, W, SIGNED, false, 0, 3>(n, q, t_best, false),
            4 => box8::<L, W, SIGNED, false, 0, 4>(n, q, t_best, false),
            5 => box8::<L, W, SIGNED, false, 0, 5>(n, q, t_best, false),
            6 => box8::<L, W, SIGNED, false, 0, 6>(n, q, t_best, false),
            _ => box8::<L, W, SIGNED, false, 0, 7>(n, q, t_best, false),
        }
    }

    /// Every variant of [`box8`] the walks may run for this ray and best hit gives the
    /// hit slots `want`; returns the full variant's result.
    fn box8_cases<L: Lanes, W: Wide>(
        n: &Node8,
        q: &RayLanes<L, W>,
        ray: &Ray,
        t_best: f32,
        want: u32,
    ) -> BoxHits<W> {
        let full = box8_dyn::<L, W, true>(n, q, t_best, true);
        assert_eq!(full.hit, want, "{ray:?} {n:?} t_best {t_best}");
        let unsigned = !(ray.t_min < 0.0);
        if unsigned {
            let b = box8_dyn::<L, W, false>(n, q, t_best, true);
            assert_eq!(b.hit, want, "unsigned {ray:?} {n:?} t_best {t_best}");
        }
        if t_best == ray.t_max {
            let b = box8_dyn::<L, W, true>(n, q, t_best, false);
            assert_eq!(b.hit, want, "no hit yet {ray:?} {n:?}");
            if unsigned {
                let b = box8_dyn::<L, W, false>(n, q, t_best, false);
                assert_eq!(b.hit, want, "unsigned, no hit yet {ray:?} {n:?}");
            }
            if !q.parallel {
                // The planes by octant: the same hits, and the same distances (`==`: but
                // for the sign of a zero).
                let b = box8_octant::<L, W, true>(n, q, t_best);
                assert_eq!(b.hit, want, "octant {ray:?} {n:?}");
                assert_eq!(b.tnear.store(), full.tnear.store(), "octant {ray:?} {n:?}");
                if unsigned {
                    let b = box8_octant::<L, W, false>(n, q, t_best);
                    assert_eq!(b.hit, want, "unsigned octant {ray:?} {n:?}");
                }
            }
        }
        full
    }

    /// The ray preparation is `Ray::is_valid` and `PreparedRay::new`, bit for bit, on
    /// every lane type, for groups of one to four rays: zero, signed-zero, subnormal,
    /// huge and non-finite components.
    #[test]
    fn ray_preparation_is_the_core_one() {
        let mut s = 0x5555_1234_aaaa_0001u64;
        let special = [
            0.0,
            -0.0,
            1e-40,
            -1e-40,
            1e30,
            -3e38,
            f32::INFINITY,
            f32::NAN,
        ];
        let (mut prepared, mut group) = (0, Vec::new());
        for _ in 0..20_000 {
            let mut ray = ray(&mut s);
            for a in 0..3 {
                if next(&mut s) < 0.15 {
                    ray.dir[a] = special[(next(&mut s) * 8.0) as usize];
                }
                if next(&mut s) < 0.02 {
                    ray.origin[a] = special[(next(&mut s) * 8.0) as usize];
                }
            }
            match (next(&mut s) * 50.0) as u32 {
                0 => ray.t_max = f32::NAN,
                1 => ray.t_min = f32::NAN,
                2 => ray.dir = [0.0, -0.0, 0.0],
                3 => ray.dir = [1e-40, -1e-39, 0.0],
                _ => {}
            }
            group.push(ray);
            if group.len() < 1 + (next(&mut s) * 8.0) as usize {
                continue;
            }
            prepared += check_group::<Portable, Pair<Portable>>(&group);
            #[cfg(target_arch = "x86_64")]
            {
                check_group::<crate::lanes::Sse, Pair<crate::lanes::Sse>>(&group);
                if has_avx2() {
                    check_group::<crate::lanes::Sse, crate::lanes::Avx8>(&group);
                }
            }
            group.clear();
        }
        assert!(prepared > 10_000, "only {prepared} valid rays");
    }

    /// Prepares one to eight rays together: each is valid as `Ray::is_valid` says, and a
    /// valid one's lanes are `PreparedRay::new`'s values. Returns the valid rays.
    fn check_group<L: Lanes, W: Wide>(group: &[Ray]) -> u32 {
        let p = super::Prepared::new::<W>(group);
        assert_eq!(p.valid >> group.len(), 0);
        for (i, ray) in group.iter().enumerate() {
            assert_eq!(p.valid >> i & 1 != 0, ray.is_valid(), "{ray:?}");
            if ray.is_valid() {
                let q = RayLanes::<L, W>::from_prepared(&p, ray, i);
                check_prepared(&q, &PreparedRay::new(ray), ray);
            }
        }
        p.valid.count_ones()
    }

    fn check_prepared<L: Lanes, W: Wide>(q: &RayLanes<L, W>, r: &PreparedRay, ray: &Ray) {
        let bits = |v: [f32; 3]| v.map(f32::to_bits);
        let lane7 = |l: &[W; 3]| [l[0].store()[7], l[1].store()[7], l[2].store()[7]];
        let lane0 = |l: &[L; 3]| [l[0].store()[0], l[1].store()[0], l[2].store()[0]];
        assert_eq!(bits(lane7(&q.org)), bits(r.org.to_array()), "{ray:?}");
        let inv = lane7(&q.ninv).map(|x| -x);
        assert_eq!(bits(inv), bits(r.inv_dir.to_array()), "{ray:?}");
        assert_eq!(bits(q.dir), bits(r.dir.to_array()), "{ray:?}");
        let s = ShearLanes::<L>::prepare(ray);
        assert_eq!(bits(lane0(&s.s)), bits([r.sx, r.sy, r.sz]), "{ray:?}");
        assert_eq!((s.kx, s.ky, q.kz), (r.kx, r.ky, r.kz), "{ray:?}");
        assert_eq!(q.parallel, r.parallel, "{ray:?}");
        let t = [q.t_min.store()[5], q.t_max.store()[1], q.t_max_s];
        assert_eq!(bits(t), bits([r.t_min, r.t_max, r.t_max]), "{ray:?}");
        assert_eq!(q.t_min4.store()[3].to_bits(), r.t_min.to_bits(), "{ray:?}");
    }

    /// A node of eight random boxes (all slots used), and the boxes.
    fn random_node(s: &mut u64) -> (Node8, [Aabb; 8]) {
        let mut n = Node8::EMPTY;
        let mut boxes = [Aabb::EMPTY; 8];
        for (i, bx) in boxes.iter_mut().enumerate() {
            let (a, b) = (point(s), point(s));
            *bx = Aabb {
                min: a.min(b),
                max: a.max(b),
            };
            for ax in 0..3 {
                n.planes[2 * ax][i] = bx.min[ax];
                n.planes[2 * ax + 1][i] = bx.max[ax];
            }
        }
        n.used = 0xff;
        (n, boxes)
    }

    /// Each lane of the eight-box test is the scalar box test of its box, on every lane
    /// type, including the parallel path and a finite running best.
    #[test]
    fn box_lanes_are_the_scalar_test() {
        let mut s = 0x1234_5678_9abc_def1u64;
        let (mut hits, mut culled) = (0, 0);
        for _ in 0..20_000 {
            let (mut n, _) = random_node(&mut s);
            n.used = if next(&mut s) < 0.2 {
                0b0111_0111
            } else {
                0b1111_1111
            };
            let ray = ray(&mut s);
            if !ray.is_valid() {
                continue;
            }
            let r = PreparedRay::new(&ray);
            let t_best = if next(&mut s) < 0.5 {
                ray.t_max
            } else {
                value(&mut s)
            };
            let want = (0..8)
                .filter(|&i| n.used >> i & 1 != 0 && box_lane(&n, &r, i, t_best))
                .fold(0, |m, i| m | 1 << i);
            let q = PortableRay::prepare(&ray);
            let b = box8_cases(&n, &q, &ray, t_best, want);
            // A popped child re-tested against a nearer best: the full test's answer, for
            // bests a few ulps around its entry, where the culling slack decides.
            let (tnear, m, far) = (b.tnear.store(), b.m().store(), b.far.store());
            for i in (0..8).filter(|i| want >> i & 1 != 0) {
                let ulps = (next(&mut s) * 400.0) as i32 - 300;
                let nearer = f32::from_bits((tnear[i].to_bits() as i32).wrapping_add(ulps) as u32);
                if nearer.is_finite() {
                    let full = box_lane(&n, &r, i, nearer);
                    assert_eq!(
                        still_hit(ray.t_max, tnear[i], m[i], far[i], nearer),
                        full,
                        "{ray:?} lane {i} best {nearer}"
                    );
                    culled += u32::from(!full);
                }
            }
            #[cfg(target_arch = "x86_64")]
            {
                box8_cases(&n, &SseRay::prepare(&ray), &ray, t_best, want);
                if has_avx2() {
                    box8_cases(&n, &AvxRay::prepare(&ray), &ray, t_best, want);
                }
            }
            hits += want.count_ones();
        }
        assert!(hits > 10_000, "only {hits} box hits");
        assert!(culled > 300, "only {culled} re-tests culled");
    }

    /// A ray whose test misses the box around a root node's boxes misses each of them:
    /// `may_enter` keeps every ray that some used slot's scalar test hits (rays aimed at
    /// the boxes' corners and face centres as well as anywhere, where the tests come
    /// closest), and drops many that miss.
    #[test]
    fn rays_that_miss_the_scene_box_miss_every_root_box() {
        let mut s = 0x5eed_0f5c_e4e0_b0c5u64;
        let (mut kept, mut dropped) = (0, 0);
        for _ in 0..10_000 {
            let (mut n, boxes) = random_node(&mut s);
            n.used = (next(&mut s) * 255.0) as u32 + 1;
            let scene = SceneBox::around(&n).expect("finite planes");
            #[cfg(target_arch = "x86_64")]
            use crate::lanes::Sse;
            let rays: [Ray; 8] = std::array::from_fn(|_| {
                let r = ray(&mut s);
                let bx = boxes[(next(&mut s) * 8.0) as usize % 8];
                let target = match (next(&mut s) * 3.0) as u32 {
                    0 => return r,
                    1 => Vec3::select(
                        glam::BVec3::new(
                            next(&mut s) < 0.5,
                            next(&mut s) < 0.5,
                            next(&mut s) < 0.5,
                        ),
                        bx.min,
                        bx.max,
                    ),
                    _ => (bx.min + bx.max) * 0.5,
                };
                Ray::with_interval(
                    r.origin.into(),
                    target - Vec3::from(r.origin),
                    r.t_min,
                    r.t_max,
                )
            });
            let check = |enter: u32, p: &Prepared| {
                let (mut k, mut d) = (0, 0);
                for (i, r) in rays
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| p.valid >> i & 1 != 0)
                {
                    let pr = PreparedRay::new(r);
                    let hit = (0..8).any(|j| n.used >> j & 1 != 0 && box_lane(&n, &pr, j, r.t_max));
                    let enters = enter >> i & 1 != 0;
                    assert!(enters || !hit, "{r:?} hits a root box but not {scene:?}");
                    k += u32::from(hit);
                    d += u32::from(!enters);
                }
                (k, d)
            };
            let p = Prepared::new::<Pair<Portable>>(&rays);
            let (k, d) = check(p.may_enter::<Pair<Portable>>(Some(&scene)), &p);
            (kept, dropped) = (kept + k, dropped + d);
            #[cfg(target_arch = "x86_64")]
            {
                let p = Prepared::new::<Pair<Sse>>(&rays);
                assert_eq!(check(p.may_enter::<Pair<Sse>>(Some(&scene)), &p), (k, d));
                if has_avx2() {
                    let p = Prepared::new::<crate::lanes::Avx8>(&rays);
                    assert_eq!(
                        check(p.may_enter::<crate::lanes::Avx8>(Some(&scene)), &p),
                        (k, d)
                    );
                }
            }
        }
        assert!(kept > 10_000, "only {kept} rays hit a root box");
        assert!(dropped > 10_000, "only {dropped} rays left out");
    }

    /// Each lane of the four-triangle test is `intersect_triangle` of its triangle: the
    /// same hits, and `t`, `u`, `v` to the bit (signed zeros included).
    #[test]
    fn triangle_lanes_are_the_scalar_test() {
        let mut s = 0x0fed_cba9_8765_4321u64;
        let mut hits = 0;
        for k in 0..40_000 {
            let mut b = Tri4 {
                v: [[[0.0; 4]; 3]; 3],
                prim: [0; 4],
            };
            let mut tris = [[Vec3::ZERO; 3]; 4];
            for (lane, t) in tris.iter_mut().enumerate() {
                let c = point(&mut s);
                *t = match k % 5 {
                    // Small triangles around a point the ray is aimed at, and slivers.
                    0 | 1 => [c, c + point(&mut s) * 0.1, c + point(&mut s) * 0.1],
                    2 => [c, c + Vec3::X, c + Vec3::X * 2.0 + Vec3::Y * 1e-6],
                    _ => [c, point(&mut s), point(&mut s)],
                };
                for (ci, corner) in t.iter().enumerate() {
                    for a in 0..3 {
                        b.v[ci][a][lane] = corner[a];
                    }
                }
            }
            let mut ray = ray(&mut s);
            if k % 2 == 0 {
                // Aim at a lane's triangle, so that many lanes hit.
                let t = tris[k % 4];
                let aim =
                    t[0] + (t[1] - t[0]) * next(&mut s) * 0.5 + (t[2] - t[0]) * next(&mut s) * 0.5;
                let d = aim - Vec3::from(ray.origin);
                if d != Vec3::ZERO {
                    ray.dir = d.to_array();
                }
            }
            if !ray.is_valid() {
                continue;
            }
            let r = PreparedRay::new(&ray);
            let (mask, t, u, v) = {
                let q = PortableRay::prepare(&ray);
                tri4::<_, false>(&b, q.t_min4, &ShearLanes::prepare(&ray))
            };
            let (t, u, v) = (t.store(), u.store(), v.store());
            for (lane, tri) in tris.iter().enumerate() {
                let want = intersect_triangle(&r, tri[0], tri[1], tri[2]);
                assert_eq!(mask >> lane & 1 != 0, want.is_some(), "{ray:?} {tri:?}");
                if let Some(h) = want {
                    let got = [t[lane], u[lane], v[lane]].map(f32::to_bits);
                    assert_eq!(got, [h.t, h.u, h.v].map(f32::to_bits), "{ray:?} {tri:?}");
                    hits += 1;
                }
            }
            // The SSE lanes, and the any-hit walks' test (no early exit): the same lanes
            // and values.
            let mut others = vec![{
                let q = PortableRay::prepare(&ray);
                tri4::<_, true>(&b, q.t_min4, &ShearLanes::prepare(&ray))
            }];
            #[cfg(target_arch = "x86_64")]
            for any in [false, true] {
                let q = SseRay::prepare(&ray);
                let s = ShearLanes::prepare(&ray);
                let (m, t, u, v) = if any {
                    tri4::<_, true>(&b, q.t_min4, &s)
                } else {
                    tri4::<_, false>(&b, q.t_min4, &s)
                };
                let back = |x: crate::lanes::Sse| Portable::load(&x.store());
                others.push((m, back(t), back(u), back(v)));
            }
            for (m2, t2, u2, v2) in others {
                assert_eq!(m2, mask, "{ray:?}");
                for lane in 0..4 {
                    if mask >> lane & 1 != 0 {
                        let a = [t[lane], u[lane], v[lane]].map(f32::to_bits);
                        let b = [t2.store()[lane], u2.store()[lane], v2.store()[lane]];
                        assert_eq!(a, b.map(f32::to_bits), "{ray:?}");
                    }
                }
            }
        }
        assert!(hits > 10_000, "only {hits} triangle hits");
    }
}
