//! Round cubic curves, as Embree 3 defines them: the surface swept by a circle of the
//! curve's radius in the plane normal to the curve, along a cubic Bezier (or a B-spline,
//! turned into its Bezier form), open at both ends.
//!
//! The intersection is Embree's (`curve_intersector_sweep.h`): the curve is cut into
//! pieces, each bounded by a cylinder about its chord and the planes normal to the curve
//! at its ends; where the ray crosses such a bound on a piece short enough, Newton's
//! method solves for the point of the ray that lies in the curve's normal plane at `u`
//! at the radius `r(u)`, starting from where it enters (and, for the far side, leaves) the
//! bound. A hit is accepted when both equations hold within Embree's error bounds, so
//! hits agree with Embree's to about the curve's rounding; a ray that grazes the surface
//! may converge in one tracer and not the other.

use glam::{Vec3, Vec4};

use super::{CurveHit, length, unit};

/// Pieces a curve piece is cut into at each level (Embree's 8 lanes less one).
const PIECES: usize = 7;
/// Levels of cutting before Newton's method, one more where the bound is seen edge on
/// (Embree's with AVX).
const LEVELS: u32 = 2;
/// Newton steps before a start is given up.
const NEWTON_STEPS: usize = 5;

/// A cubic Bezier curve with a radius (`w`) per control point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Bezier(pub [Vec4; 4]);

impl Bezier {
    /// The point, first and second derivatives at `u`.
    pub fn eval(&self, u: f32) -> (Vec4, Vec4, Vec4) {
        let [p0, p1, p2, p3] = self.0;
        let s = 1.0 - u;
        let p = s * s * s * p0 + 3.0 * s * s * u * p1 + 3.0 * s * u * u * p2 + u * u * u * p3;
        let d = 3.0 * (s * s * (p1 - p0) + 2.0 * s * u * (p2 - p1) + u * u * (p3 - p2));
        let dd = 6.0 * (s * (p2 - 2.0 * p1 + p0) + u * (p3 - 2.0 * p2 + p1));
        (p, d, dd)
    }

    /// The box of the control points, grown by the largest radius: the swept surface lies
    /// inside it (the basis is non-negative, so neither point nor radius leaves the hull).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let r = self.0.iter().fold(0.0f32, |m, p| m.max(p.w));
        let (lo, hi) = self.0.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(p.truncate()), hi.max(p.truncate())),
        );
        (lo - r, hi + r)
    }

    fn translated(&self, by: Vec3) -> Bezier {
        Bezier(self.0.map(|p| p - by.extend(0.0)))
    }
}

/// An interval of `t`, empty when `lo > hi`.
#[derive(Clone, Copy, Debug)]
struct Span {
    lo: f32,
    hi: f32,
}

impl Span {
    const EMPTY: Span = Span {
        lo: f32::INFINITY,
        hi: f32::NEG_INFINITY,
    };
    const ALL: Span = Span {
        lo: f32::NEG_INFINITY,
        hi: f32::INFINITY,
    };

    fn and(self, o: Span) -> Span {
        Span {
            lo: self.lo.max(o.lo),
            hi: self.hi.min(o.hi),
        }
    }

    fn is_empty(&self) -> bool {
        !(self.lo <= self.hi)
    }
}

/// The line through `p0` and `p1` as the ray `t dir` (from the origin) sees it: what
/// [`Chord::cylinder`] needs for any radius, found once for a piece's two cylinders.
struct Chord {
    len: f32,
    dd: f32,
    doz: f32,
    oz: f32,
    /// `od` and `oo` of the ray against the line: `dir.o` and `o.o`, `o = -p0`.
    od: f32,
    oo: f32,
}

impl Chord {
    fn new(dir: Vec3, p0: Vec3, p1: Vec3) -> Chord {
        let axis = p1 - p0;
        // Divisions by the lengths (not products with reciprocals, which a shader
        // compiler may fuse into an approximate reciprocal square root).
        let len = length(axis);
        let dp = axis / len;
        let o = -p0;
        Chord {
            len,
            dd: dir.dot(dir),
            od: dir.dot(o),
            oo: o.dot(o),
            doz: dp.dot(dir),
            oz: dp.dot(o),
        }
    }

    /// Where the ray is within `r` of the line, and the fractions along `p0`..`p1` of its
    /// entry and exit.
    fn cylinder(&self, r: f32) -> Option<(Span, f32, f32)> {
        let Chord {
            len,
            dd,
            doz,
            oz,
            od,
            oo,
        } = *self;
        let a = dd - doz * doz;
        let b = 2.0 * (od - doz * oz);
        let c = oo - oz * oz - r * r;
        let disc = b * b - 4.0 * a * c;
        if !(disc >= 0.0) {
            return None;
        }
        if a.abs() < 16.0 * f32::EPSILON * dd.abs().max(doz * doz) {
            // Along the axis: inside for every t, or for none.
            return (c <= 0.0).then_some((Span::ALL, 0.0, 1.0));
        }
        let q = disc.sqrt();
        let rcp_2a = (2.0 * a).recip();
        let (t0, t1) = ((-b - q) * rcp_2a, (-b + q) * rcp_2a);
        let span = Span { lo: t0, hi: t1 };
        Some((span, (t0 * doz + oz) / len, (t1 * doz + oz) / len))
    }
}

/// Where the ray `t dir` is on the side of the plane through `p` that `n` points to.
fn half_space(dir: Vec3, p: Vec3, n: Vec3) -> Span {
    let (a, b) = (-p.dot(n), dir.dot(n));
    let t = -a / b;
    if b > 0.0 {
        Span {
            lo: t,
            hi: f32::INFINITY,
        }
    } else if b < 0.0 {
        Span {
            lo: f32::NEG_INFINITY,
            hi: t,
        }
    } else if a >= 0.0 {
        Span::ALL
    } else {
        Span::EMPTY
    }
}

/// The round cubic `curve` against the ray `org + t dir`: the nearest hit in
/// `[t_min, t_max]`.
pub(crate) fn round_cubic(
    org: Vec3,
    dir: Vec3,
    (t_min, t_max): (f32, f32),
    curve: &Bezier,
) -> Option<CurveHit> {
    // Solve near the curve, with the ray's origin moved to its middle.
    let center = 0.5 * (curve.0[0].truncate() + curve.0[3].truncate());
    let dt = (center - org).dot(dir) / dir.dot(dir);
    let near = Sweep {
        curve: curve.translated(org + dt * dir),
        dir,
        dt,
        range: (t_min, t_max),
    };
    let mut best: Option<CurveHit> = None;
    near.pieces(&mut best);
    best
}

/// A level of cutting: the curve at its `PIECES + 1` cuts (`u`, the point, the
/// derivative scaled to a piece's handle), its depth, and the next piece to visit.
#[derive(Clone, Copy)]
struct Cut {
    at: [(f32, Vec4, Vec4); PIECES + 1],
    depth: u32,
    next: usize,
}

impl Cut {
    const EMPTY: Cut = Cut {
        at: [(0.0, Vec4::ZERO, Vec4::ZERO); PIECES + 1],
        depth: 0,
        next: PIECES,
    };
}

/// One ray against one curve, in the curve's frame moved to the ray.
struct Sweep {
    curve: Bezier,
    dir: Vec3,
    /// Where the moved origin is along the ray.
    dt: f32,
    range: (f32, f32),
}

impl Sweep {
    /// The end of the interval still open: the best hit's distance, or `t_max`.
    fn t_far(&self, best: &Option<CurveHit>) -> f32 {
        best.as_ref().map_or(self.range.1, |h| h.t)
    }

    /// Cuts the curve into pieces, and each piece whose bound the ray crosses again, down
    /// to the last level, where Newton's method starts from where the ray enters and
    /// leaves the bound. Depth first, pieces in order, with an explicit stack (the
    /// kernel's twin has no recursion).
    fn pieces(&self, best: &mut Option<CurveHit>) {
        // Each level being cut, with its next piece.
        let mut stack = [Cut::EMPTY; LEVELS as usize + 1];
        stack[0] = self.cut(0.0, 1.0, 1);
        let mut sp = 1;
        while sp > 0 {
            let k = stack[sp - 1].next;
            if k == PIECES {
                sp -= 1;
                continue;
            }
            stack[sp - 1].next = k + 1;
            let level = &stack[sp - 1];
            let depth = level.depth;
            if let Some((ua, ub)) = self.piece(level, k, best) {
                stack[sp] = self.cut(ua, ub, depth + 1);
                sp += 1;
            }
        }
    }

    /// `u0..u1` cut into `PIECES` at `depth`: the curve at each cut, its derivative
    /// scaled to a piece's Bezier handle.
    fn cut(&self, u0: f32, u1: f32, depth: u32) -> Cut {
        // Products with the reciprocals, as Embree writes them (and as a shader compiler
        // may rewrite a division by a constant).
        let dscale = (u1 - u0) * (1.0 / (3.0 * PIECES as f32));
        let mut at = [(0.0, Vec4::ZERO, Vec4::ZERO); PIECES + 1];
        for (k, a) in at.iter_mut().enumerate() {
            let u = u0 + (u1 - u0) * (k as f32 * (1.0 / PIECES as f32));
            let (p, d, _) = self.curve.eval(u);
            *a = (u, p, d * dscale);
        }
        Cut { at, depth, next: 0 }
    }

    /// Piece `k` of `level`: `Some` of its interval when the ray crosses its bound and it
    /// is to be cut again, else `None` (after Newton's method at the last level).
    fn piece(&self, level: &Cut, k: usize, best: &mut Option<CurveHit>) -> Option<(f32, f32)> {
        let ((ua, p0, d0), (ub, p3, d3)) = (level.at[k], level.at[k + 1]);
        let depth = level.depth;
        let (p1, p2) = (p0 + d0, p3 - d3);
        // Cylinders about the chord that hold the piece's surface, and are held by it.
        let chord = (p3 - p0).truncate();
        let off = |d: Vec4| {
            let d = d.truncate();
            let l = chord.dot(chord);
            if l > 0.0 {
                length(d - chord * (d.dot(chord) / l))
            } else {
                length(d)
            }
        };
        let bend = off(d0).max(off(d3));
        let rmax = p0.w.max(p1.w).max(p2.w).max(p3.w).max(0.0);
        let rmin = p0.w.min(p1.w).min(p2.w).min(p3.w);
        let r_outer = (rmax + bend) * (1.0 + 2.0 * f32::EPSILON);
        let r_inner = ((rmin - bend) * (1.0 - 2.0 * f32::EPSILON)).max(0.0);
        let (a, b) = (p0.truncate(), p3.truncate());
        let axis = Chord::new(self.dir, a, b);
        let (outer, ua_out, ub_out) = axis.cylinder(r_outer)?;
        let span = Span {
            lo: self.range.0 - self.dt,
            hi: self.t_far(best) - self.dt,
        }
        .and(outer)
        .and(half_space(self.dir, a, d0.truncate()))
        .and(half_space(self.dir, b, -d3.truncate()));
        if span.is_empty() {
            return None;
        }
        // The part of the span inside the inner cylinder holds no surface.
        let inner = axis.cylinder(r_inner);
        let (front, back) = match inner {
            Some((i, _, _)) => (
                Span {
                    lo: span.lo,
                    hi: span.hi.min(i.lo),
                },
                Span {
                    lo: span.lo.max(i.hi),
                    hi: span.hi,
                },
            ),
            None => (span, span),
        };
        // Where the ray grazes the inner cylinder, Newton's method needs a shorter piece.
        let grazes = |t: f32, f: f32| {
            let across = t * self.dir - (a + f * (b - a));
            unit(self.dir).dot(unit(across)).abs() < 0.3
        };
        let edge_on = match inner {
            Some((i, f0, f1)) => grazes(i.lo, f0) || grazes(i.hi, f1),
            None => true,
        };
        let last = if edge_on { LEVELS + 1 } else { LEVELS };
        if depth < last {
            return (!front.is_empty() || !back.is_empty()).then_some((ua, ub));
        }
        let piece_u = |f: f32| ua + (ub - ua) * f.clamp(0.0, 1.0);
        if !front.is_empty() {
            self.newton(piece_u(ua_out), front.lo, best);
        }
        if !back.is_empty() && back.lo + self.dt <= self.t_far(best) {
            self.newton(piece_u(ub_out), back.hi, best);
        }
        None
    }

    /// Newton's method on `(u, t)` from a start: the ray's point `q = t dir` lies in the
    /// curve's normal plane at `u` (`f = (q - p).T = 0`) at its radius (`g = |q - p|_perp -
    /// r = 0`). Keeps the hit if it is nearer than the best.
    fn newton(&self, mut u: f32, mut t: f32, best: &mut Option<CurveHit>) {
        let dir = self.dir;
        let len_dir = length(dir);
        let (lo, hi) = self.curve_box();
        let p_err = 16.0 * f32::EPSILON * lo.abs().max(hi.abs()).truncate().max_element();
        let w_err = 16.0 * f32::EPSILON * hi.w;
        for _ in 0..NEWTON_STEPS {
            let q = t * dir;
            let (p, dp, ddp) = self.curve.eval(u);
            let (p3, dp3, ddp3) = (p.truncate(), dp.truncate(), ddp.truncate());
            let r = q - p3;
            let len_r = length(r);
            let r_err = (16.0 * f32::EPSILON * len_dir * t).max(p_err);
            let len_dp = length(dp3);
            let tan = dp3 / len_dp;
            // d/du of dp / |dp|.
            let dtan = (ddp3 * dp3.dot(dp3) - dp3 * dp3.dot(ddp3)) / (len_dp * len_dp * len_dp);
            let cos_err = p_err / len_dp;
            let f = r.dot(tan);
            let f_err = len_r * p_err + r_err + cos_err * (1.0 + len_r);
            let dfdu = (-dp3).dot(tan) + r.dot(dtan);
            let dfdt = dir.dot(tan);
            let k = r.dot(r) - f * f;
            let dkdu = r.dot(-dp3) - f * dfdu;
            let dkdt = r.dot(dir) - f * dfdt;
            let sqrt_k = k.sqrt();
            let g = sqrt_k - p.w;
            let g_err = r_err + f_err + w_err;
            let dgdu = dkdu / sqrt_k - dp.w;
            let dgdt = dkdt / sqrt_k;
            // Solve [[dfdu, dfdt], [dgdu, dgdt]] (du, dt) = (f, g).
            let det = dfdu * dgdt - dfdt * dgdu;
            let du = (dgdt * f - dfdt * g) / det;
            let dtt = (dfdu * g - dgdu * f) / det;
            u -= du;
            t -= dtt;
            if f.abs() < f_err && g.abs() < g_err {
                let t_hit = t + self.dt;
                let ok =
                    self.range.0 <= t_hit && t_hit <= self.t_far(best) && (0.0..=1.0).contains(&u);
                if ok && best.is_none_or(|b| t_hit < b.t) {
                    // Embree's normal: across the tube, bent by the radius' slope.
                    let rn = unit(r);
                    let across = dp.w * rn + dp3;
                    let normal = dp3.cross(rn).cross(across);
                    *best = Some(CurveHit {
                        t: t_hit,
                        u,
                        normal,
                    });
                }
                return;
            }
        }
    }

    /// The box of the moved control points with their radii (`w` the largest).
    fn curve_box(&self) -> (Vec4, Vec4) {
        self.curve.0.iter().fold(
            (Vec4::splat(f32::INFINITY), Vec4::splat(f32::NEG_INFINITY)),
            |(lo, hi), &p| (lo.min(p), hi.max(p)),
        )
    }
}
