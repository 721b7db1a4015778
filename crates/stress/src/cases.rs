//! The stress cases: generators for every group (see [`CASE_GROUPS`]).

use std::path::{Path, PathBuf};

use bvhtrace_core::{
    BuildOptions, BuilderKind, FlatBvh, Instance, MISS, Ray, TraceOptions, Traversal, Triangle,
    trace_rays,
};
use glam::{DQuat, DVec3, Vec3};

use crate::geom::{
    IndexedMesh, Rng, affine_from_f64, aim_at_placed_vertices_and_edges, aim_at_vertices_and_edges,
    box_mesh, camera_rays, count_zero_area, icosphere, inside_points, is_inside, to_f64,
    unit_icosphere,
};
use crate::offset::{geometric_normal, hit_point, offset_ray_origin};
use crate::{Case, Expect, InputInfo, PrecisionSetup, Size, SurfacePair, SurfaceProbe};

/// The case groups, in run order: `(name, what it exercises)`. A group makes one case or
/// several named `GROUP-...`.
pub const CASE_GROUPS: &[(&str, &str)] = &[
    (
        "watertight",
        "closed icospheres, and every closed mesh of the shared scenes folder (closedness by edge counting after welding identical positions): rays from inside aimed exactly at every vertex and at points of every edge; a miss is an escape",
    ),
    (
        "offset",
        "offset-1e2 .. offset-1e7: a closed icosphere of radius 1 translated by 10^k, rays from inside and a camera moved with it",
    ),
    (
        "scale",
        "scale-1e-9 .. scale-1e9: a closed icosphere scaled about the origin, rays from inside and a camera scaled with it",
    ),
    (
        "scale-limit",
        "scale-limit-1e-20 .. scale-limit-1e19: the scale case beyond the guaranteed range, where the triangle test's products under- or overflow (measured, not guaranteed)",
    ),
    (
        "stadium",
        "a small detailed closed mesh inside a closed box 1e4 times larger: near camera, rays from inside both, rays from the walls",
    ),
    (
        "slivers",
        "closed cylinders whose sides are slivers of aspect 1e2, 1e4, 1e6, 1e3 units long, plus random slivers (aspect 10..1e6) spanning the scene",
    ),
    (
        "coincident",
        "many coincident triangles (exact duplicates of a closed icosphere) and coplanar overlapping triangles (some with rotated corner order)",
    ),
    (
        "degenerate",
        "zero-area (point, repeated-corner, collinear) and needle triangles mixed in index order with a closed icosphere, sharing its vertices and edges",
    ),
    (
        "extreme-rays",
        "axis-parallel rays with +0/-0 components, 1e-30 and subnormal components, huge and tiny directions, empty and infinite intervals, negative t_min, NaN/inf/zero rays (INVALID_RAY), grazing rays in a face's plane",
    ),
    (
        "self-hits",
        "secondary rays from surface hit points (point from barycentrics), without offset and with the Wachter-Binder origin offset, reflected and transmitted",
    ),
    (
        "deep",
        "exponentially spaced triangles with the midpoint builder, max_depth 1000, one triangle per leaf: a tree deeper than the GPU full-stack kernel's 64 entries",
    ),
    (
        "precision-limit",
        "two parallel squares gap 1e-2, 1e-3, 1e-4 apart, translated by 1e0 .. 1e8 (4 per decade), rays from 1 unit away and from `offset` away: where f32 stops separating them",
    ),
    (
        "instances",
        "two levels: a closed icosphere instanced rotated, scaled by 1e-6 and 1e6, non-uniformly (axis ratios to 1e6), mirrored, translated by 1e5, and all of these at once; rays from inside each instance aimed exactly at its world-space vertices and edge points (targets placed in f64); a miss is an escape",
    ),
    (
        "motion",
        "motion-t0 .. motion-after, motion-flip-*: a closed icosphere moving, turning and growing over 3 time steps, one turning inside out over 2 (every winding flips; flat at mid-shutter), and one placed by moving instances (still, moving and stretching, mirrored), each traced at one time (the shutter's ends exactly, a step, between steps, outside the shutter): rays from inside at that time and a camera; every walk of moving meshes, both ways of bounding time",
    ),
    (
        "curves",
        "curves-round-linear .. curves-round-bspline: straight strands of each kind with rays aimed at each segment's axis (known hits) and past it (known misses), triangles beside them, zero-length segments, radius 0, a radius 50 times a segment's length, rays along the strands and a camera; against the tree's brute force (no f64 oracle for curves)",
    ),
];

/// What the cases are made for: their size, and the shared scenes folder (holding `glb/`)
/// the cases of real meshes read; without one those are skipped, saying so. This crate
/// reads no environment variable and looks for no folder: a front end passes the one its
/// user named.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CaseOptions {
    /// How big to make them.
    pub size: Size,
    /// The shared scenes folder.
    pub scenes: Option<PathBuf>,
}

impl CaseOptions {
    /// Cases of `size`, without real meshes.
    pub fn new(size: Size) -> CaseOptions {
        CaseOptions { size, scenes: None }
    }

    /// The same, the real meshes read from `scenes` (its `glb/` folder).
    pub fn with_scenes(self, scenes: Option<PathBuf>) -> CaseOptions {
        CaseOptions { scenes, ..self }
    }
}

/// Every case.
pub fn cases_sized(opts: &CaseOptions) -> Vec<Case> {
    CASE_GROUPS
        .iter()
        .flat_map(|(g, _)| generate(g, opts))
        .collect()
}

/// The cases named in `names` (each a case name, a group name, or a prefix followed by
/// `-`: `offset` selects every `offset-*`); all cases when `names` is empty. Only the groups
/// needed are generated. Unknown names are an error listing the groups.
pub fn select_cases(names: &[String], opts: &CaseOptions) -> Result<Vec<Case>, String> {
    let names: Vec<&str> = names
        .iter()
        .flat_map(|n| n.split(','))
        .map(str::trim)
        .filter(|n| !n.is_empty())
        .collect();
    if names.is_empty() {
        return Ok(cases_sized(opts));
    }
    // The longest group that names or prefixes `n` (`scale-limit-1e14` is not `scale`).
    let group_of = |n: &str| {
        CASE_GROUPS
            .iter()
            .map(|(g, _)| *g)
            .filter(|g| n == *g || n.starts_with(&format!("{g}-")))
            .max_by_key(|g| g.len())
    };
    let mut groups: Vec<&str> = Vec::new();
    for n in &names {
        match group_of(n) {
            Some(g) => {
                if !groups.contains(&g) {
                    groups.push(g);
                }
            }
            None => {
                return Err(format!(
                    "unknown case '{n}' (groups: {})",
                    CASE_GROUPS
                        .iter()
                        .map(|(g, _)| *g)
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
            }
        }
    }
    let mut out = Vec::new();
    for (g, _) in CASE_GROUPS {
        if !groups.contains(g) {
            continue;
        }
        for c in generate(g, opts) {
            if names
                .iter()
                .any(|n| c.name == *n || c.name.starts_with(&format!("{n}-")))
            {
                out.push(c);
            }
        }
    }
    for n in &names {
        if !out
            .iter()
            .any(|c| c.name == *n || c.name.starts_with(&format!("{n}-")))
        {
            return Err(format!(
                "no case named '{n}' at this size (its group made none: see the notes of `--case {}`)",
                group_of(n).unwrap_or(n)
            ));
        }
    }
    Ok(out)
}

fn generate(group: &str, opts: &CaseOptions) -> Vec<Case> {
    let (size, scenes) = (opts.size, opts.scenes.as_deref());
    match group {
        "watertight" => watertight(size, scenes),
        "offset" => offsets(size),
        "scale" => scales(size),
        "scale-limit" => scale_limits(size),
        "stadium" => vec![stadium(size)],
        "slivers" => vec![slivers(size)],
        "coincident" => vec![coincident(size)],
        "degenerate" => vec![degenerate(size)],
        "extreme-rays" => vec![extreme_rays()],
        "self-hits" => vec![self_hits(size, scenes)],
        "deep" => vec![deep(size)],
        "precision-limit" => vec![precision_limit(size)],
        "instances" => instance_cases(size),
        "motion" => crate::motion::motion_cases(size),
        "curves" => crate::curves::curve_cases(size),
        _ => Vec::new(),
    }
}

pub(crate) fn quick(size: Size) -> bool {
    size == Size::Quick
}

/// Edge fractions for the watertightness rays.
pub(crate) fn fractions(size: Size) -> &'static [f64] {
    if quick(size) {
        &[0.5, 1.0 / 3.0]
    } else {
        &[0.5, 0.25, 1.0 / 3.0, 0.9, 1e-3]
    }
}

/// Adds `from`-rays aimed at every vertex and edge point of `mesh` when `from` is inside
/// `closed` (the f64 oracle's parity): `MustHit`; else a note and `Oracle`.
pub(crate) fn add_inside_rays(
    case: &mut Case,
    mesh: &IndexedMesh,
    closed: &[Triangle],
    from: Vec3,
    fr: &[f64],
    what: &str,
) {
    let rays = aim_at_vertices_and_edges(mesh, from, fr);
    if is_inside(closed, from, 0.0) {
        case.push_rays(rays, Expect::MustHit);
    } else {
        case.notes.push(format!(
            "{what}: the point {from} is not verified inside (the f32 input changed shape); its {} rays are compared with the oracle instead",
            rays.len()
        ));
        case.push_rays(rays, Expect::Oracle);
    }
}

/// Keeps at most `max` rays, evenly spaced (deterministic).
fn thin(rays: Vec<Ray>, max: usize) -> Vec<Ray> {
    if rays.len() <= max {
        return rays;
    }
    let n = rays.len();
    (0..max).map(|i| rays[i * n / max]).collect()
}

pub(crate) fn finish_input(case: &mut Case) {
    case.input.zero_area_triangles = count_zero_area(&case.tris);
}

fn watertight(size: Size, scenes: Option<&Path>) -> Vec<Case> {
    let mut out = Vec::new();
    let mut c = Case::new(
        "watertight",
        "closed icospheres (subdivisions 1..5, radius 1, shared vertices); from the centre, an off-centre point and a point near the surface, rays aimed exactly at every vertex and at points of every edge",
    );
    let subdivs: &[u32] = if quick(size) { &[1, 3] } else { &[2, 4, 5] };
    let mut scene = IndexedMesh::default();
    let mut spheres = Vec::new();
    for (k, &n) in subdivs.iter().enumerate() {
        let center = DVec3::new(3.0 * k as f64, 0.1 * k as f64, -0.2 * k as f64);
        let s = icosphere(n, center, 1.0);
        scene.append(&s);
        spheres.push((center, s));
    }
    c.tris = scene.triangles();
    for (center, s) in &spheres {
        let st = s.triangles();
        for rel in [
            DVec3::ZERO,
            DVec3::new(0.3, -0.2, 0.1),
            DVec3::new(0.52, 0.61, -0.4),
        ] {
            add_inside_rays(
                &mut c,
                s,
                &st,
                (*center + rel).as_vec3(),
                fractions(size),
                "icosphere",
            );
        }
    }
    set_budget(&mut c, size);
    finish_input(&mut c);
    out.push(c);

    // Real closed meshes.
    let dir = scenes.map(|d| d.join("glb"));
    let Some(dir) = dir.filter(|d| d.is_dir()) else {
        let mut skip = Case::new("watertight-real", "real closed meshes");
        skip.notes.push(
            "SKIP: no shared scenes folder with a glb/ folder (`bvhtrace stress` takes $BVHTRACE_SCENES, or shared/scenes above the working directory)".into(),
        );
        out.push(skip);
        return out;
    };
    let wanted: Vec<PathBuf> = if quick(size) {
        ["bunny_npm_3k.glb", "khronos_box.glb"]
            .iter()
            .map(|f| dir.join(f))
            .collect()
    } else {
        let mut v: Vec<PathBuf> = std::fs::read_dir(&dir)
            .map(|r| r.filter_map(|e| e.ok().map(|e| e.path())).collect())
            .unwrap_or_default();
        v.retain(|p| p.extension().is_some_and(|e| e == "glb"));
        v.sort();
        v
    };
    let mut skipped = Vec::new();
    for path in wanted {
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let Some(spec) = path.to_str() else { continue };
        let scene = match bvhtrace_scene::load(spec) {
            Ok(s) => s,
            Err(e) => {
                skipped.push(format!("{stem}: {e}"));
                continue;
            }
        };
        if scene.triangle_count() > 300_000 {
            skipped.push(format!("{stem}: over 300k triangles"));
            continue;
        }
        let tm = scene.flatten();
        let mesh = IndexedMesh {
            positions: tm.positions,
            indices: tm.indices,
        }
        .welded();
        let cl = mesh.closedness();
        if !cl.is_closed() {
            skipped.push(format!(
                "{stem}: not closed ({} boundary, {} non-manifold, {} inconsistent edges)",
                cl.boundary_edges, cl.nonmanifold_edges, cl.inconsistent_edges
            ));
            continue;
        }
        let tris = mesh.triangles();
        let points = inside_points(&tris, 2);
        if points.is_empty() {
            skipped.push(format!("{stem}: closed, but no inside point found"));
            continue;
        }
        let mut c = Case::new(
            format!("watertight-{stem}"),
            format!(
                "{stem}.glb from the shared scenes ({} triangles, closed after welding identical positions): rays from {} inside points aimed at every vertex and at points of the edges",
                tris.len(),
                points.len()
            ),
        );
        let cap = if quick(size) { 12_000 } else { 150_000 };
        for p in &points {
            let rays = aim_at_vertices_and_edges(&mesh, *p, fractions(size));
            let n = rays.len();
            let rays = thin(rays, cap);
            if rays.len() < n {
                c.notes.push(format!(
                    "from {p}: {} of {n} vertex/edge rays (evenly thinned)",
                    rays.len()
                ));
            }
            c.push_rays(rays, Expect::MustHit);
        }
        c.tris = tris;
        set_budget(&mut c, size);
        finish_input(&mut c);
        out.push(c);
    }
    if let Some(first) = out.first_mut() {
        for s in skipped {
            first.notes.push(format!("real mesh skipped: {s}"));
        }
    }
    out
}

/// Triangle tests the oracle may spend on one case (`rays x triangles`).
fn budget(size: Size) -> usize {
    if quick(size) { 30_000_000 } else { 150_000_000 }
}

/// Sets the oracle sample so that `sample x triangles` stays within the budget.
pub(crate) fn set_budget(case: &mut Case, size: Size) {
    case.oracle_budget = (budget(size) / case.tris.len().max(1)).clamp(256, 1 << 20);
}

/// A mesh placed by `scale` and `offset` as a case: inside rays and a camera.
fn placed_sphere_case(
    name: String,
    description: String,
    scale: f64,
    offset: DVec3,
    size: Size,
) -> Case {
    let base = unit_icosphere(if quick(size) { 3 } else { 4 });
    let (mesh, placement) = base.placed(scale, offset);
    let mut c = Case::new(name, description);
    c.tris = mesh.triangles();
    c.input = InputInfo {
        exact: placement.exact,
        merged_vertices: placement.merged_vertices,
        zero_area_triangles: 0,
    };
    for rel in [DVec3::ZERO, DVec3::new(0.3, -0.2, 0.1)] {
        let from = (offset + rel * scale).as_vec3();
        let t = c.tris.clone();
        add_inside_rays(&mut c, &mesh, &t, from, fractions(size), "inside");
    }
    let (w, h) = if quick(size) { (32, 32) } else { (96, 96) };
    let eye = offset + DVec3::new(0.4, 0.3, 3.0) * scale;
    let mut cam = camera_rays(eye, offset, 45.0, w, h);
    // Half the camera rays with directions scaled too (t then in scene units).
    for (i, r) in cam.iter_mut().enumerate() {
        if i % 2 == 1 {
            let d = Vec3::from(r.dir).as_dvec3() * scale;
            r.dir = d.as_vec3().to_array();
        }
    }
    c.push_rays(cam, Expect::Oracle);
    set_budget(&mut c, size);
    finish_input(&mut c);
    if placement.merged_vertices > 0 || placement.new_zero_area > 0 {
        c.notes.push(format!(
            "input merged: rounding to f32 merged {} vertices and made {} triangles zero-area",
            placement.merged_vertices, placement.new_zero_area
        ));
    }
    c
}

fn offsets(size: Size) -> Vec<Case> {
    (2..=7)
        .map(|e| {
            let o = 10f64.powi(e);
            placed_sphere_case(
                format!("offset-1e{e}"),
                format!("closed icosphere of radius 1 centred at 1e{e} * (1, -0.5, 0.25); rays from inside and a camera 3 units away, moved with it"),
                1.0,
                DVec3::new(o, -0.5 * o, 0.25 * o),
                size,
            )
        })
        .collect()
}

fn scales(size: Size) -> Vec<Case> {
    [-9, -6, -3, 3, 6, 9]
        .iter()
        .map(|&e| {
            let s = 10f64.powi(e);
            placed_sphere_case(
                format!("scale-1e{e}"),
                format!("closed icosphere centred at (0.3, 0.1, -0.2), all scaled by 1e{e} about the origin; rays from inside and a camera scaled with it (half the camera directions scaled too)"),
                s,
                DVec3::new(0.3, 0.1, -0.2) * s,
                size,
            )
        })
        .collect()
}

fn scale_limits(size: Size) -> Vec<Case> {
    let exps: &[i32] = if quick(size) {
        &[-16, 14]
    } else {
        &[-20, -18, -16, -14, -12, 12, 13, 14, 16, 19]
    };
    exps.iter()
        .map(|&e| {
            let s = 10f64.powi(e);
            let mut c = placed_sphere_case(
                format!("scale-limit-1e{e}"),
                format!("beyond the guaranteed range: the scale case at 1e{e} (camera rays with unit and with scaled directions), to find where f32 runs out"),
                s,
                DVec3::new(0.3, 0.1, -0.2) * s,
                size,
            );
            c.guaranteed = false;
            c
        })
        .collect()
}

fn stadium(size: Size) -> Case {
    let q = quick(size);
    let mut c = Case::new(
        "stadium",
        "a closed icosphere of radius 1 (the detailed mesh) inside a closed box of half-size 1e4: near camera, rays from inside the sphere (vertex/edge aims), random rays inside the stadium, rays from near the walls aimed at the sphere",
    );
    let center = DVec3::new(0.2, 0.1, -0.3);
    let sphere = icosphere(if q { 3 } else { 5 }, center, 1.0);
    let walls = box_mesh(DVec3::splat(-1e4), DVec3::new(1e4, 1.2e4, 0.9e4));
    let mut scene = sphere.clone();
    scene.append(&walls);
    c.tris = scene.triangles();
    let st = sphere.triangles();
    add_inside_rays(
        &mut c,
        &sphere,
        &st,
        center.as_vec3(),
        fractions(size),
        "sphere",
    );
    let wt = walls.triangles();
    add_inside_rays(
        &mut c,
        &walls,
        &wt,
        DVec3::new(10.0, -20.0, 5.0).as_vec3(),
        &[0.5, 0.25, 1e-3],
        "stadium",
    );
    let (w, h) = if q { (32, 32) } else { (96, 96) };
    c.push_rays(
        camera_rays(center + DVec3::new(0.5, 0.4, 3.0), center, 60.0, w, h),
        Expect::Oracle,
    );
    let mut rng = Rng::new(7);
    let n = if q { 1500 } else { 20_000 };
    let mut inside = Vec::new();
    while inside.len() < n {
        let p = rng.in_box(DVec3::splat(-9e3), DVec3::splat(8e3));
        if (p - center).length() > 2.0 {
            inside.push(Ray::new(p.as_vec3(), rng.unit().as_vec3()));
        }
    }
    c.push_rays(inside, Expect::MustHit);
    let mut far = Vec::new();
    for _ in 0..n / 2 {
        let o = center + rng.unit() * 0.9e4;
        let target = center + rng.unit() * 0.9;
        far.push(Ray::new(o.as_vec3(), (target - o).as_vec3()));
    }
    c.push_rays(far, Expect::Oracle);
    set_budget(&mut c, size);
    finish_input(&mut c);
    c
}

/// A closed cylinder along +x from `x0`, `len` long, radius `r`, `n` segments, centred
/// on the line `(y, z)`; caps are fans around a centre vertex.
fn cylinder(x0: f64, len: f64, r: f64, n: u32, y: f64, z: f64) -> IndexedMesh {
    let mut positions = Vec::new();
    for end in 0..2 {
        let x = x0 + len * end as f64;
        for i in 0..n {
            let a = std::f64::consts::TAU * i as f64 / n as f64;
            positions.push(DVec3::new(x, y + r * a.cos(), z + r * a.sin()).as_vec3());
        }
    }
    positions.push(DVec3::new(x0, y, z).as_vec3());
    positions.push(DVec3::new(x0 + len, y, z).as_vec3());
    let (c0, c1) = (2 * n, 2 * n + 1);
    let mut indices = Vec::new();
    for i in 0..n {
        let j = (i + 1) % n;
        indices.push([i, j, n + j]);
        indices.push([i, n + j, n + i]);
        indices.push([c0, j, i]);
        indices.push([c1, n + i, n + j]);
    }
    IndexedMesh { positions, indices }
}

fn slivers(size: Size) -> Case {
    let q = quick(size);
    let mut c = Case::new(
        "slivers",
        "closed cylinders 1e3 long whose side triangles have aspect 1e2, 1e4 and 1e6 (rays from inside aimed at every vertex and edge point, many nearly along the axis), plus random slivers of aspect 10..1e6 spanning the scene seen by a camera",
    );
    let len = 1e3;
    let segs = if q { 12 } else { 32 };
    let mut scene = IndexedMesh::default();
    let mut cyls = Vec::new();
    for (k, aspect) in [1e2, 1e4, 1e6].into_iter().enumerate() {
        // Side width (chord) = len / aspect.
        let chord = len / aspect;
        let r = chord / (2.0 * (std::f64::consts::PI / segs as f64).sin());
        // Away from the random slivers (z in [-20, 20]): a ray from inside a cylinder hits
        // nothing but its cylinder first.
        let cyl = cylinder(0.0, len, r, segs, 10.0 * k as f64, 100.0);
        scene.append(&cyl);
        cyls.push((cyl, r, 10.0 * k as f64));
    }
    let mut rng = Rng::new(11);
    let n_random = if q { 600 } else { 6000 };
    let mut random = Vec::new();
    for _ in 0..n_random {
        let a = rng.in_box(DVec3::new(0.0, -20.0, -20.0), DVec3::new(len, 40.0, 20.0));
        let b = rng.in_box(DVec3::new(0.0, -20.0, -20.0), DVec3::new(len, 40.0, 20.0));
        let l = (b - a).length();
        let aspect = 10f64.powf(rng.range(1.0, 6.0));
        let side = (b - a).cross(rng.unit()).normalize();
        let m = (a + b) * 0.5 + side * (l / aspect);
        random.push([a.as_vec3(), b.as_vec3(), m.as_vec3()]);
    }
    c.tris = scene.triangles();
    c.tris.extend(random);
    for (cyl, r, y) in &cyls {
        let ct = cyl.triangles();
        for x in [len * 0.5, len * 1e-3, len * 0.9997] {
            let from = DVec3::new(x, y + 0.3 * r, 100.0 - 0.2 * r).as_vec3();
            add_inside_rays(
                &mut c,
                cyl,
                &ct,
                from,
                &[0.5, 0.25, 1e-3, 0.999, 1e-5],
                "cylinder",
            );
            let k = if q { 300 } else { 3000 };
            let dirs: Vec<Ray> = (0..k)
                .map(|_| Ray::new(from, rng.unit().as_vec3()))
                .collect();
            if is_inside(&ct, from, 0.0) {
                c.push_rays(dirs, Expect::MustHit);
            }
        }
    }
    let (w, h) = if q { (48, 24) } else { (160, 80) };
    c.push_rays(
        camera_rays(
            DVec3::new(500.0, 10.0, 900.0),
            DVec3::new(500.0, 10.0, 50.0),
            70.0,
            w,
            h,
        ),
        Expect::Oracle,
    );
    c.push_rays(
        camera_rays(
            DVec3::new(-50.0, 12.0, 3.0),
            DVec3::new(500.0, 8.0, 0.0),
            20.0,
            w,
            h,
        ),
        Expect::Oracle,
    );
    set_budget(&mut c, size);
    finish_input(&mut c);
    c
}

/// Exact duplicates of one triangle in the coincident case: more than 65,535.
const LONG_WALK: usize = 70_000;

fn coincident(size: Size) -> Case {
    let q = quick(size);
    let n = if q { 20_000 } else { 200_000 };
    let mut c = Case::new(
        "coincident",
        format!(
            "{n} triangles: exact duplicates of a closed 80-triangle icosphere (coincident, same corner order: ties go to the lowest index), and coplanar overlapping triangles in z = -3 (a tenth of them repeated with rotated corner order); plus a stack of {LONG_WALK} duplicates of one triangle that rays along +-x must test in full (known answer: its lowest index)"
        ),
    );
    let base = icosphere(1, DVec3::ZERO, 1.0);
    let bt = base.triangles();
    let copies = n / 2 / bt.len();
    for _ in 0..copies {
        c.tris.extend_from_slice(&bt);
    }
    let mut rng = Rng::new(5);
    let mut plane = Vec::new();
    while c.tris.len() + plane.len() < n {
        let p = rng.in_box(DVec3::new(-2.0, -2.0, -3.0), DVec3::new(2.0, 2.0, -3.0));
        let s = rng.range(0.2, 2.0);
        let t: Triangle = [0, 1, 2].map(|_| {
            let d = rng.unit();
            (p + DVec3::new(d.x, d.y, 0.0) * s).as_vec3()
        });
        plane.push(t);
        if rng.f64() < 0.1 {
            plane.push([t[1], t[2], t[0]]);
        }
    }
    c.tris.extend(plane);
    c.tris.truncate(n);
    // A stack of exact duplicates of one triangle, away from the rest: a ray through it
    // must test every one of them (all tie), more loop trips than a GPU driver may allow
    // one invocation (lavapipe stops every loop of an invocation after 65,535 trips in
    // all). The answer is known: the lowest index of the stack.
    let first = c.tris.len() as u32;
    let stack: Triangle = [
        Vec3::new(20.0, -1.0, -1.0),
        Vec3::new(20.0, 1.0, -1.0),
        Vec3::new(20.0, 0.0, 1.5),
    ];
    c.tris.extend(std::iter::repeat_n(stack, LONG_WALK));
    for k in 0..16 {
        let (y, z) = (rng.range(-0.4, 0.4), rng.range(-0.5, 0.3));
        let jitter = DVec3::new(0.0, rng.range(-0.01, 0.01), rng.range(-0.01, 0.01));
        for (x, dx) in [(25.0, -1.0), (15.0, 1.0)] {
            let o = DVec3::new(x, y, z).as_vec3();
            let d = (DVec3::new(dx, 0.0, 0.0) + jitter * (k % 2) as f64).as_vec3();
            c.push_rays([Ray::new(o, d)], Expect::Prim(first));
        }
    }
    add_inside_rays(
        &mut c,
        &base,
        &bt,
        Vec3::new(0.1, 0.2, -0.05),
        &[0.5],
        "sphere",
    );
    let (w, h) = if q { (24, 24) } else { (64, 64) };
    c.push_rays(
        camera_rays(
            DVec3::new(0.5, 0.7, 6.0),
            DVec3::new(0.0, 0.0, -1.5),
            60.0,
            w,
            h,
        ),
        Expect::Oracle,
    );
    let k = if q { 400 } else { 2000 };
    let up: Vec<Ray> = (0..k)
        .map(|_| {
            let o = rng.in_box(DVec3::new(-2.0, -2.0, -5.0), DVec3::new(2.0, 2.0, -4.0));
            Ray::new(o.as_vec3(), (DVec3::Z + rng.unit() * 0.3).as_vec3())
        })
        .collect();
    c.push_rays(up, Expect::Oracle);
    set_budget(&mut c, size);
    finish_input(&mut c);
    c
}

fn degenerate(size: Size) -> Case {
    let q = quick(size);
    let mut c = Case::new(
        "degenerate",
        "a closed icosphere with zero-area triangles on its vertices and edges (points, repeated corners, collinear corners with the f32 midpoint), needles, and exactly collinear triangles in space, all shuffled in index order",
    );
    let sphere = icosphere(if q { 3 } else { 4 }, DVec3::ZERO, 1.0);
    let st = sphere.triangles();
    let mut rng = Rng::new(13);
    let mut degen: Vec<Triangle> = Vec::new();
    let p = &sphere.positions;
    for (i, (a, b)) in sphere.edges().into_iter().enumerate() {
        let (a, b) = (p[a as usize], p[b as usize]);
        match i % 5 {
            0 => degen.push([a, a, a]),
            1 => degen.push([a, b, b]),
            2 => degen.push([a, (a + b) * 0.5, b]),
            3 => degen.push([b, a, a]),
            _ => {}
        }
    }
    for _ in 0..(if q { 200 } else { 2000 }) {
        // Exactly collinear: small integers times a power of two.
        let o = (rng.in_box(DVec3::splat(-4.0), DVec3::splat(4.0)) * 8.0).round() / 8.0;
        let d = DVec3::new(
            rng.below(5) as f64 - 2.0,
            rng.below(5) as f64 - 2.0,
            rng.below(3) as f64,
        ) / 4.0;
        degen.push([o.as_vec3(), (o + d).as_vec3(), (o + 2.0 * d).as_vec3()]);
        // A needle: collinear but for one ulp-scale nudge.
        let e = (o + 3.0 * d).as_vec3();
        degen.push([o.as_vec3(), (o + d).as_vec3() + Vec3::splat(1e-6), e]);
    }
    // Shuffle the union deterministically so prim indices interleave.
    let mut all: Vec<(bool, Triangle)> = st
        .iter()
        .map(|t| (false, *t))
        .chain(degen.iter().map(|t| (true, *t)))
        .collect();
    for i in (1..all.len()).rev() {
        let j = rng.below(i + 1);
        all.swap(i, j);
    }
    c.tris = all.iter().map(|x| x.1).collect();
    for rel in [DVec3::ZERO, DVec3::new(0.3, -0.2, 0.1)] {
        add_inside_rays(
            &mut c,
            &sphere,
            &st,
            rel.as_vec3(),
            fractions(size),
            "sphere",
        );
    }
    let (w, h) = if q { (32, 32) } else { (96, 96) };
    c.push_rays(
        camera_rays(DVec3::new(0.5, 0.4, 7.0), DVec3::ZERO, 75.0, w, h),
        Expect::Oracle,
    );
    // Rays along the collinear triangles' own lines, and across them.
    let mut along = Vec::new();
    for t in degen.iter().step_by(7) {
        let d = (t[2] - t[0]).as_dvec3();
        if d != DVec3::ZERO {
            along.push(Ray::new((t[0].as_dvec3() - d).as_vec3(), d.as_vec3()));
            along.push(Ray::new(
                (t[1].as_dvec3() + rng.unit()).as_vec3(),
                (-rng.unit()).as_vec3(),
            ));
        }
    }
    c.push_rays(along, Expect::Oracle);
    set_budget(&mut c, size);
    finish_input(&mut c);
    c.notes.push(format!(
        "{} degenerate or needle triangles among {}",
        degen.len(),
        c.tris.len()
    ));
    c
}

fn extreme_rays() -> Case {
    let mut c = Case::new(
        "extreme-rays",
        "a unit square in z = 0 (prims 0, 1), a closed box [2,3]^3 (prims 2..13), an icosphere at (-3, 0.5, 0.5): rays with signed-zero, 1e-30, subnormal and huge/tiny direction components, empty/infinite/negative intervals, invalid rays, grazing rays",
    );
    let (cube, ball, ball_c) = extreme_scene(&mut c);
    signed_zero_rays(&mut c);
    inside_box_rays(&mut c, &cube);
    tiny_component_rays(&mut c, ball_c);
    magnitude_rays(&mut c, ball_c);
    interval_rays(&mut c);
    invalid_rays(&mut c);
    grazing_rays(&mut c, &ball);
    ball_grid_rays(&mut c, ball_c);
    c.oracle_budget = c.rays.len();
    finish_input(&mut c);
    c
}

/// Puts the scene into `c`: a unit square in z = 0, a closed box [2,3]^3 and an
/// icosphere; returns the box, the icosphere and its centre.
fn extreme_scene(c: &mut Case) -> (IndexedMesh, IndexedMesh, DVec3) {
    let square = IndexedMesh {
        positions: vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ],
        indices: vec![[0, 1, 2], [0, 2, 3]],
    };
    let cube = box_mesh(DVec3::splat(2.0), DVec3::splat(3.0));
    let ball_c = DVec3::new(-3.0, 0.5, 0.5);
    let ball = icosphere(2, ball_c, 1.0);
    let mut scene = square.clone();
    scene.append(&cube);
    scene.append(&ball);
    c.tris = scene.triangles();
    (cube, ball, ball_c)
}

/// Axis-parallel rays at the square with every signed-zero combination.
fn signed_zero_rays(c: &mut Case) {
    let v = Vec3::new;
    let z = [0.0f32, -0.0];
    for &(x, y, e) in &[
        (0.75f32, 0.25f32, Expect::Prim(0)),
        (0.25, 0.75, Expect::Prim(1)),
        (0.5, 0.5, Expect::MustHit),
        (0.0, 0.0, Expect::MustHit),
        (1.0, 1.0, Expect::MustHit),
        (0.0, 0.5, Expect::MustHit),
        (1.0, 0.3, Expect::MustHit),
        (0.3, 0.0, Expect::MustHit),
        (1.0, 0.0, Expect::MustHit),
        (0.0, 1.0, Expect::MustHit),
        (1.000_000_1, 0.5, Expect::Miss),
        (-1e-30, 0.5, Expect::Miss),
        (0.5, 1.000_000_1, Expect::Miss),
        // Subnormal origin coordinates: exactly inside / outside the edge x = 0.
        (1e-40, 0.5, Expect::MustHit),
        (-1e-40, 0.5, Expect::Miss),
    ] {
        for zx in z {
            for zy in z {
                c.push_rays([Ray::new(v(x, y, -2.0), v(zx, zy, 1.0))], e);
                c.push_rays([Ray::new(v(x, y, 2.0), v(zx, zy, -1.0))], e);
            }
        }
    }
}

/// Rays from inside the box (signed-zero axis directions, at corners and edges), and
/// rays moving inside its face plane x = 2.
fn inside_box_rays(c: &mut Case, cube: &IndexedMesh) {
    let v = Vec3::new;
    let z = [0.0f32, -0.0];
    // B. The box from inside: axis directions with signed zeros, corners and edges.
    for from in [v(2.5, 2.5, 2.5), v(2.25, 2.625, 2.375)] {
        for axis in 0..3 {
            for sign in [1.0f32, -1.0] {
                for zx in z {
                    for zy in z {
                        let mut d = [zx, zy, zx];
                        d[(axis + 1) % 3] = zy;
                        d[axis] = sign;
                        c.push_rays([Ray::new(from, Vec3::from(d))], Expect::MustHit);
                    }
                }
            }
        }
        c.push_rays(
            aim_at_vertices_and_edges(cube, from, &[0.5, 0.25, 1e-3]),
            Expect::MustHit,
        );
    }
    // On the face plane x = 2, moving inside it along +y / -y / +z.
    for d in [
        v(0.0, 1.0, 0.0),
        v(-0.0, -1.0, 0.0),
        v(0.0, 0.0, 1.0),
        v(-0.0, 0.3, 1.0),
    ] {
        c.push_rays([Ray::new(v(2.0, 2.5, 2.5), d)], Expect::Oracle);
        c.push_rays([Ray::new(v(2.0, 1.0, 2.5), d)], Expect::Oracle);
    }
}

/// Rays with tiny direction components: 1e-30 (normal) and 1e-40 (subnormal).
fn tiny_component_rays(c: &mut Case, ball_c: DVec3) {
    let v = Vec3::new;
    // C. Tiny components: 1e-30 (normal) and 1e-40 (subnormal, flushed to zero).
    for t in [1e-30f32, 1e-40] {
        c.push_rays(
            [Ray::new(v(0.75, 0.25, -2.0), v(t, -t, 1.0))],
            Expect::Prim(0),
        );
        c.push_rays(
            [Ray::new(v(0.25, 0.75, 2.0), v(-t, t, -1.0))],
            Expect::Prim(1),
        );
        c.push_rays([Ray::new(v(2.5, 2.5, 2.5), v(1.0, t, -t))], Expect::MustHit);
        c.push_rays([Ray::new(ball_c.as_vec3(), v(t, 1.0, t))], Expect::MustHit);
        c.push_rays(
            [Ray::new(ball_c.as_vec3(), v(-t, -t, -1.0))],
            Expect::MustHit,
        );
    }
}

/// Rays with direction magnitudes from 1e-30 to 1e38, and one whose t would be subnormal.
fn magnitude_rays(c: &mut Case, ball_c: DVec3) {
    let v = Vec3::new;
    // D. Direction magnitudes from 1e-30 to 1e38.
    for m in [1e38f32, 1e30, 1e10, 1e-10, 1e-30] {
        c.push_rays(
            [Ray::new(v(0.75, 0.25, -2.0), v(0.0, 0.0, m))],
            Expect::Prim(0),
        );
        c.push_rays(
            [Ray::new(ball_c.as_vec3(), v(0.3, -0.2, 0.5) * m)],
            Expect::MustHit,
        );
    }
    // t would be subnormal (2 / 3e38): no defined answer beyond the contract.
    c.push_rays(
        [Ray::new(v(0.75, 0.25, -2.0), v(0.0, 0.0, 3e38))],
        Expect::Unspecified,
    );
}

/// Rays at the square with empty, infinite, negative and boundary intervals.
fn interval_rays(c: &mut Case) {
    let v = Vec3::new;
    // E. Intervals.
    let o = v(0.75, 0.25, -2.0);
    let iv = |t0: f32, t1: f32| Ray::with_interval(o, Vec3::Z, t0, t1);
    let up2 = f32::from_bits(2f32.to_bits() + 1);
    for t in [0.0f32, 2.0, 1e30, f32::INFINITY] {
        c.push_rays([iv(t, t)], Expect::Miss); // [t, t) is empty
    }
    c.push_rays([iv(0.0, 2.0)], Expect::Miss); // t_max excluded
    c.push_rays([iv(2.0, up2)], Expect::Prim(0)); // t_min included
    c.push_rays([iv(up2, f32::INFINITY)], Expect::Miss);
    c.push_rays([iv(3.0, 1.0)], Expect::Miss); // t_min > t_max
    c.push_rays([iv(0.0, -1.0)], Expect::Miss);
    c.push_rays([iv(f32::NEG_INFINITY, f32::INFINITY)], Expect::Prim(0));
    c.push_rays([iv(0.0, f32::INFINITY)], Expect::Prim(0));
    c.push_rays([iv(-0.0, f32::MAX)], Expect::Prim(0));
    // Behind the origin with a negative t_min.
    let behind = v(0.75, 0.25, 2.0);
    c.push_rays(
        [
            Ray::with_interval(behind, Vec3::Z, f32::NEG_INFINITY, -1.0),
            Ray::with_interval(behind, Vec3::Z, -2.0, 0.0),
        ],
        Expect::Prim(0),
    );
    c.push_rays(
        [Ray::with_interval(behind, Vec3::Z, -1.9, 0.0)],
        Expect::Miss,
    );
    // Origin on the square: t = 0 is in [0, inf) and in [-0, inf).
    for t0 in [0.0f32, -0.0] {
        c.push_rays(
            [Ray::with_interval(
                v(0.75, 0.25, 0.0),
                Vec3::Z,
                t0,
                f32::INFINITY,
            )],
            Expect::Prim(0),
        );
    }
    c.push_rays(
        [Ray::with_interval(
            v(0.75, 0.25, 0.0),
            Vec3::Z,
            1e-45,
            f32::INFINITY,
        )],
        Expect::Miss,
    );
}

/// Invalid rays, rays with all-subnormal directions and rays from huge finite origins.
fn invalid_rays(c: &mut Case) {
    let v = Vec3::new;
    let o = v(0.75, 0.25, -2.0);
    // F. Invalid rays.
    let (nan, inf) = (f32::NAN, f32::INFINITY);
    for r in [
        Ray::new(v(nan, 0.0, 0.0), Vec3::Z),
        Ray::new(v(0.0, inf, 0.0), Vec3::Z),
        Ray::new(v(0.0, 0.0, -inf), Vec3::Z),
        Ray::new(Vec3::ZERO, v(0.0, nan, 1.0)),
        Ray::new(Vec3::ZERO, v(inf, 0.0, 1.0)),
        Ray::new(Vec3::ZERO, v(0.0, 0.0, -inf)),
        Ray::new(Vec3::ZERO, v(0.0, 0.0, 0.0)),
        Ray::new(Vec3::ZERO, v(-0.0, -0.0, -0.0)),
        Ray::new(Vec3::ZERO, v(0.0, -0.0, 0.0)),
        Ray::with_interval(o, Vec3::Z, nan, 1.0),
        Ray::with_interval(o, Vec3::Z, 0.0, nan),
        Ray::with_interval(o, Vec3::Z, nan, nan),
        Ray::with_interval(v(nan, nan, nan), v(nan, nan, nan), nan, nan),
    ] {
        c.push_rays([r], Expect::Invalid);
    }
    // A direction whose components are all subnormal: valid, but zero once flushed.
    c.push_rays(
        [Ray::new(v(0.75, 0.25, -2.0), v(0.0, 0.0, 1e-40))],
        Expect::Unspecified,
    );
    c.push_rays(
        [Ray::new(v(2.5, 2.5, 2.5), v(1e-39, -1e-39, 1e-40))],
        Expect::Unspecified,
    );
    // Huge finite origins.
    c.push_rays([Ray::new(v(0.75, 0.25, -3e38), Vec3::Z)], Expect::Oracle);
    c.push_rays([Ray::new(v(3e38, 0.5, 0.5), Vec3::NEG_X)], Expect::Oracle);
}

/// Grazing rays: in the square's plane, along the box's edge and face, and along
/// icosphere faces' edges in their planes.
fn grazing_rays(c: &mut Case, ball: &IndexedMesh) {
    let v = Vec3::new;
    // G. Grazing: in the square's plane, along its edge and diagonal, and in icosphere
    // faces' planes along their edges.
    for (org, d) in [
        (v(-1.0, 0.5, 0.0), v(1.0, 0.0, 0.0)),
        (v(-1.0, 0.5, 0.0), v(1.0, -0.0, -0.0)),
        (v(-1.0, 0.0, 0.0), v(1.0, 0.0, 0.0)),
        (v(-1.0, -1.0, 0.0), v(1.0, 1.0, 0.0)),
        (v(0.5, -1.0, 0.0), v(0.0, 1.0, 0.0)),
        (v(-1.0, 0.5, 0.0), v(1.0, 1e-30, 0.0)),
        (v(-1.0, 0.5, 1e-30), v(1.0, 0.0, 0.0)),
        (v(2.0, 2.0, 1.0), v(0.0, 0.0, 1.0)), // along the box's edge x = y = 2
        (v(1.0, 2.5, 2.0), v(1.0, 0.0, 0.0)), // along the box's face z = 2
    ] {
        c.push_rays([Ray::new(org, d)], Expect::Oracle);
    }
    let bt = ball.triangles();
    for t in bt.iter().step_by(2) {
        let (a, b) = (t[0].as_dvec3(), t[1].as_dvec3());
        let e = b - a;
        c.push_rays(
            [Ray::new((a - e * 3.0).as_vec3(), e.as_vec3())],
            Expect::Oracle,
        );
        let m = (a + b + t[2].as_dvec3()) / 3.0;
        c.push_rays(
            [Ray::new((m - e * 2.0).as_vec3(), e.as_vec3())],
            Expect::Oracle,
        );
    }
}

/// Axis-parallel rays at the icosphere from a grid, with signed zeros.
fn ball_grid_rays(c: &mut Case, ball_c: DVec3) {
    let v = Vec3::new;
    let z = [0.0f32, -0.0];
    // H. Axis-parallel rays at the icosphere from a grid, signed zeros.
    for i in 0..16 {
        for j in 0..16 {
            let (a, b) = (
                ball_c.y - 1.2 + 2.4 * i as f64 / 15.0,
                ball_c.z - 1.2 + 2.4 * j as f64 / 15.0,
            );
            let zx = z[(i + j) % 2];
            c.push_rays(
                [Ray::new(
                    DVec3::new(ball_c.x - 3.0, a, b).as_vec3(),
                    v(1.0, zx, -zx),
                )],
                Expect::Oracle,
            );
            c.push_rays(
                [Ray::new(
                    DVec3::new(a - 3.5, ball_c.y + 3.0, b).as_vec3(),
                    v(zx, -1.0, zx),
                )],
                Expect::Oracle,
            );
        }
    }
}

fn self_hits(size: Size, scenes: Option<&Path>) -> Case {
    let q = quick(size);
    let mut c = Case::new(
        "self-hits",
        "closed icospheres of radius 1 at (0.3,-0.2,0.1) and (100,200,-150) (and bunny_npm_3k when the shared folder exists): camera rays find hit points; from each, rays reflected and transmitted, from the barycentric hit point (t_min = 0) and from offset_ray_origin(p, n)",
    );
    let sub = if q { 3 } else { 4 };
    let mut objects: Vec<(IndexedMesh, DVec3)> = Vec::new();
    for center in [DVec3::new(0.3, -0.2, 0.1), DVec3::new(100.0, 200.0, -150.0)] {
        objects.push((icosphere(sub, center, 1.0), center));
    }
    if let Some(dir) = scenes {
        let path = dir.join("glb").join("bunny_npm_3k.glb");
        if let Some(scene) = path.to_str().and_then(|p| bvhtrace_scene::load(p).ok()) {
            let tm = scene.flatten();
            let m = IndexedMesh {
                positions: tm.positions,
                indices: tm.indices,
            };
            let (lo, hi) = m.bounds();
            let mid = ((lo + hi) * 0.5).as_dvec3();
            let s = 2.0 / (hi - lo).max_element() as f64;
            let at = DVec3::new(-5.0, 1.0, 0.5);
            objects.push((m.placed(s, at - mid * s).0, at));
        } else {
            c.notes
                .push("bunny_npm_3k.glb not loaded: icospheres only".into());
        }
    } else {
        c.notes
            .push("SKIP bunny: no shared scenes folder; icospheres only".into());
    }
    let mut scene = IndexedMesh::default();
    for (m, _) in &objects {
        scene.append(m);
    }
    c.tris = scene.triangles();
    let bvh = match FlatBvh::build(&c.tris, &BuildOptions::default()) {
        Ok(b) => b,
        Err(e) => {
            c.notes.push(format!("build failed: {e}"));
            return c;
        }
    };
    let (w, h) = if q { (24, 24) } else { (64, 64) };
    let mut rng = Rng::new(17);
    let per_hit = if q { 2 } else { 4 };
    for (_, center) in &objects {
        let eye = *center + DVec3::new(0.7, 0.9, 3.2);
        let prim = camera_rays(eye, *center, 45.0, w, h);
        let hits = trace_rays(&bvh, &prim, &TraceOptions::closest(Traversal::FullStack)).hits;
        for (r, hit) in prim.iter().zip(&hits) {
            if !hit.is_hit() {
                continue;
            }
            let tri = &c.tris[hit.prim as usize];
            let p = hit_point(tri, hit);
            let n = geometric_normal(tri).as_dvec3();
            if n == DVec3::ZERO {
                continue;
            }
            let front = if n.dot(Vec3::from(r.dir).as_dvec3()) < 0.0 {
                n
            } else {
                -n
            };
            for k in 0..per_hit {
                let side = if k % 2 == 0 { front } else { -front };
                let d = rng.hemisphere(side).as_vec3();
                let origin = hit.prim;
                c.push_rays(
                    [Ray::new(p, d)],
                    Expect::Secondary {
                        origin,
                        offset: false,
                    },
                );
                let po = offset_ray_origin(p, side.as_vec3());
                c.push_rays(
                    [Ray::new(po, d)],
                    Expect::Secondary {
                        origin,
                        offset: true,
                    },
                );
            }
        }
    }
    set_budget(&mut c, size);
    finish_input(&mut c);
    c
}

fn deep(size: Size) -> Case {
    let q = quick(size);
    let n: i32 = if q { 90 } else { 120 };
    let mut c = Case::new(
        "deep",
        format!(
            "{n} triangles in the planes x = 3^(i-40) (same cross-section), midpoint builder with max_depth 1000 and one triangle per leaf: a chain {} levels deep; rays along +-x between the planes (known answers), oblique rays, misses",
            n - 1
        ),
    );
    c.build = BuildOptions {
        builder: BuilderKind::Midpoint,
        max_depth: 1000,
        max_leaf_size: 1,
        ..Default::default()
    };
    // Ratio 3: the midpoint of the centroid range always lies above the second largest,
    // so every split peels off one triangle.
    let xs: Vec<f32> = (0..n).map(|i| 3f64.powi(i - 40) as f32).collect();
    c.tris = xs
        .iter()
        .map(|&x| {
            [
                Vec3::new(x, -1.0, -1.0),
                Vec3::new(x, 1.0, -1.0),
                Vec3::new(x, 0.0, 1.5),
            ]
        })
        .collect();
    let mut rng = Rng::new(19);
    let k = if q { 1500 } else { 20_000 };
    for _ in 0..k {
        let i = rng.below(n as usize - 1);
        let ox = xs[i] as f64 * rng.range(1.1, 1.9);
        let (y, z) = (rng.range(-0.4, 0.4), rng.range(-0.5, 0.3));
        let o = DVec3::new(ox, y, z).as_vec3();
        c.push_rays([Ray::new(o, Vec3::X)], Expect::Prim(i as u32 + 1));
        c.push_rays([Ray::new(o, Vec3::NEG_X)], Expect::Prim(i as u32));
        // Oblique, and far out of the cross-section.
        c.push_rays([Ray::new(o, rng.unit().as_vec3())], Expect::Oracle);
        c.push_rays(
            [Ray::new(DVec3::new(ox, 2.0 + y, z).as_vec3(), Vec3::X)],
            Expect::Miss,
        );
    }
    let last = *xs.last().unwrap_or(&1.0);
    c.push_rays(
        [Ray::new(Vec3::new(2.0 * last, 0.1, 0.0), Vec3::NEG_X)],
        Expect::Prim(n as u32 - 1),
    );
    c.push_rays(
        [Ray::new(Vec3::new(-1.0, 0.1, 0.0), Vec3::X)],
        Expect::Prim(0),
    );
    c.oracle_budget = c.rays.len();
    finish_input(&mut c);
    c
}

/// One placement of an instance, in f64 (rounded once to the f32 transform).
#[derive(Clone, Copy, Debug)]
struct Place {
    scale: DVec3,
    rotation: DQuat,
    translation: DVec3,
}

fn rot(axis: [f64; 3], degrees: f64) -> DQuat {
    DQuat::from_axis_angle(DVec3::from_array(axis).normalize(), degrees.to_radians())
}

/// Three rotations about unrelated axes (one by 90 degrees, whose f32 matrix has
/// near-zero entries instead of zeros).
fn rotations() -> [DQuat; 3] {
    [
        rot([1.0, 2.0, 3.0], 37.0),
        rot([-0.3, 1.0, 0.2], 123.0),
        rot([0.0, 0.0, 1.0], 90.0),
    ]
}

/// The placements of each single-transform instance case: `(name, what, placements)`.
fn instance_placements() -> Vec<(&'static str, &'static str, Vec<Place>)> {
    let [r1, r2, r3] = rotations();
    let p = |s: DVec3, r: DQuat, t: DVec3| Place {
        scale: s,
        rotation: r,
        translation: t,
    };
    let near = [
        DVec3::ZERO,
        DVec3::new(3.0, 0.5, -1.0),
        DVec3::new(-2.5, 2.0, 1.5),
    ];
    let uniform = |s: f64| {
        vec![
            p(DVec3::splat(s), r1, near[0] * s),
            p(DVec3::splat(s), r2, near[1] * s),
            p(DVec3::splat(s), r3, near[2] * s),
        ]
    };
    let far = DVec3::new(1e5, -0.5e5, 0.25e5);
    vec![
        (
            "rotated",
            "rotated about three unrelated axes (37, 123 and 90 degrees), radius 1, a few units apart",
            uniform(1.0),
        ),
        (
            "scale-1e-6",
            "rotated and scaled by 1e-6, a few radii apart near the origin",
            uniform(1e-6),
        ),
        (
            "scale-1e6",
            "rotated and scaled by 1e6, a few radii apart",
            uniform(1e6),
        ),
        (
            "nonuniform",
            "rotated and scaled non-uniformly: (1e-3, 1, 1e3) at the origin, (1e3, 1e-2, 1) at (3e3, 0, 0), (1e-2, 1e2, 1) at (0, -3e3, 500)",
            vec![
                p(DVec3::new(1e-3, 1.0, 1e3), r1, DVec3::ZERO),
                p(DVec3::new(1e3, 1e-2, 1.0), r2, DVec3::new(3e3, 0.0, 0.0)),
                p(DVec3::new(1e-2, 1e2, 1.0), r3, DVec3::new(0.0, -3e3, 500.0)),
            ],
        ),
        (
            "mirrored",
            "mirrored (determinant < 0: the flattened scene swaps corners 1 and 2): scales (-1, 1, 1), (1, -2, 0.5) and (-1, -1, -1), rotated",
            vec![
                p(DVec3::new(-1.0, 1.0, 1.0), r1, near[0]),
                p(DVec3::new(1.0, -2.0, 0.5), r2, near[1]),
                p(DVec3::splat(-1.0), r3, near[2]),
            ],
        ),
        (
            "offset-1e5",
            "rotated, radius 1 and 2, translated by 1e5 * (1, -0.5, 0.25) (two, 3 units apart) and 1e5 * (-0.3, 1, 0.7)",
            vec![
                p(DVec3::ONE, r1, far),
                p(DVec3::ONE, r2, far + near[1]),
                p(DVec3::splat(2.0), r3, DVec3::new(-0.3e5, 1e5, 0.7e5)),
            ],
        ),
    ]
}

/// A closed unit icosphere instanced at each placement, as one two-level case: from
/// `inside` points of each instance (object space, placed in f64 and rounded once), rays
/// aimed exactly at the instance's world-space vertices and at points of its edges (the
/// targets placed in f64 from the object-space corners and the f32 transform). `MustHit`
/// where the origin is inside the instance's flattened world triangles (checked), at most
/// `cap` rays per origin (evenly thinned); at most `quick_sample` rays compared with the
/// oracle at quick size (every ray's escape is checked whatever the sample).
fn instanced_sphere_case(
    name: String,
    description: String,
    places: &[Place],
    inside: &[DVec3],
    (cap, quick_sample): (usize, usize),
    size: Size,
) -> Case {
    let mesh = unit_icosphere(if quick(size) { 2 } else { 3 });
    let tris = mesh.triangles();
    let n = tris.len();
    let instances: Vec<Instance> = places
        .iter()
        .map(|p| Instance::new(0, affine_from_f64(p.scale, p.rotation, p.translation)))
        .collect();
    let mut c = Case::instanced(name, description, vec![tris], instances.clone());
    for (k, inst) in instances.iter().enumerate() {
        let m = to_f64(&inst.transform);
        let world = c.tris[k * n..(k + 1) * n].to_vec();
        for rel in inside {
            let from = m.transform_point3(*rel).as_vec3();
            let rays = aim_at_placed_vertices_and_edges(
                &mesh,
                |p| m.transform_point3(p),
                from,
                fractions(size),
            );
            let all = rays.len();
            let rays = thin(rays, cap);
            if rays.len() < all {
                c.notes.push(format!(
                    "instance {k}, from {from}: {} of {all} vertex/edge rays (evenly thinned)",
                    rays.len()
                ));
            }
            if is_inside(&world, from, 0.0) {
                c.push_rays(rays, Expect::MustHit);
            } else {
                c.notes.push(format!(
                    "instance {k}: the point {from} is not verified inside (rounding to f32 moved it out); its {} rays are compared with the oracle instead",
                    rays.len()
                ));
                c.push_rays(rays, Expect::Oracle);
            }
        }
    }
    c.notes.push(format!(
        "two levels: {} instances of one closed icosphere ({n} triangles)",
        instances.len()
    ));
    set_budget(&mut c, size);
    if quick(size) {
        c.oracle_budget = c.oracle_budget.min(quick_sample);
    }
    finish_input(&mut c);
    c
}

fn instance_cases(size: Size) -> Vec<Case> {
    let inside: &[DVec3] = if quick(size) {
        &[DVec3::ZERO, DVec3::new(0.3, -0.2, 0.1)]
    } else {
        &[
            DVec3::ZERO,
            DVec3::new(0.3, -0.2, 0.1),
            DVec3::new(0.52, 0.61, -0.4),
        ]
    };
    let mut out = Vec::new();
    let mut every = Vec::new();
    for (name, what, places) in instance_placements() {
        out.push(instanced_sphere_case(
            format!("instances-{name}"),
            format!("a closed icosphere instanced {} times, {what}; rays from inside each instance aimed exactly at its world-space vertices and edge points", places.len()),
            &places,
            inside,
            (usize::MAX, 2048),
            size,
        ));
        every.extend(places);
    }
    out.push(instanced_sphere_case(
        "instances-mixed".into(),
        format!(
            "every placement of the other instances-* cases at once: {} instances of one closed icosphere in one two-level BVH, scales 1e-6 .. 1e6, some overlapping or nested; rays from inside each instance aimed at its world-space vertices and edge points",
            every.len()
        ),
        &every,
        &inside[1..2],
        (if quick(size) { 400 } else { 4000 }, 1024),
        size,
    ));
    out
}

/// Closest hit of a ray over triangles given in f64 (Moller-Trumbore in f64): the
/// intended answer for geometry that f32 cannot hold exactly.
fn closest_f64(tris: &[[DVec3; 3]], ray: &Ray) -> u32 {
    let o = Vec3::from(ray.origin).as_dvec3();
    let d = Vec3::from(ray.dir).as_dvec3();
    let mut best = (f64::INFINITY, MISS);
    for (i, t) in tris.iter().enumerate() {
        let e1 = t[1] - t[0];
        let e2 = t[2] - t[0];
        let p = d.cross(e2);
        let det = e1.dot(p);
        if det == 0.0 {
            continue;
        }
        let s = o - t[0];
        let u = s.dot(p) / det;
        let qv = s.cross(e1);
        let v = d.dot(qv) / det;
        let tt = e2.dot(qv) / det;
        if u >= 0.0 && v >= 0.0 && u + v <= 1.0 && tt >= ray.t_min as f64 && tt < best.0 {
            best = (tt, i as u32);
        }
    }
    best.1
}

fn precision_limit(size: Size) -> Case {
    let q = quick(size);
    let gaps = [1e-2, 1e-3, 1e-4];
    let mut c = Case::new(
        "precision-limit",
        "pairs of parallel squares (normal (0.3, 0.2, 1)) a gap 1e-2, 1e-3 or 1e-4 apart, centred near offset*(1,1,1) for offsets 1e0..1e8 (4 per decade); the lower square has the lower primitive indices, so merged input shows as the wrong surface; rays from 1 unit away (near) and from `offset` away (far)",
    );
    let n = DVec3::new(0.3, 0.2, 1.0).normalize();
    let t1 = n.cross(DVec3::X).normalize();
    let t2 = n.cross(t1);
    let mut setup = PrecisionSetup::default();
    let mut exact_tris: Vec<[DVec3; 3]> = Vec::new();
    let mut rng = Rng::new(23);
    let per = if q { 12 } else { 40 };
    let mut probes_todo: Vec<(u32, bool, Ray)> = Vec::new();
    for k in 0..=32 {
        let o = 10f64.powf(k as f64 / 4.0);
        for (j, &gap) in gaps.iter().enumerate() {
            let pair = setup.pairs.len() as u32;
            let center = DVec3::splat(o) + DVec3::new(0.35, -0.35, 0.0) * j as f64;
            let half = 0.1 * (o * 1e-5).max(1.0);
            let square = |c: DVec3| {
                let p = [
                    c - t1 * half - t2 * half,
                    c + t1 * half - t2 * half,
                    c + t1 * half + t2 * half,
                    c - t1 * half + t2 * half,
                ];
                [[p[0], p[1], p[2]], [p[0], p[2], p[3]]]
            };
            let upper = square(center);
            let lower = square(center - n * gap);
            let mut merged = 0;
            for (lt, ut) in lower.iter().zip(&upper) {
                for (l, u) in lt.iter().zip(ut) {
                    // The lower corner rounds to a point on the upper square's f32 plane
                    // position: the same f32 corner.
                    if l.as_vec3() == u.as_vec3() {
                        merged += 1;
                    }
                }
            }
            setup.pairs.push(SurfacePair {
                offset: o,
                gap,
                merged_corners: merged,
            });
            for t in lower {
                exact_tris.push(t);
                c.tris.push(t.map(|p| p.as_vec3()));
                setup.prim_surface.push((pair, false));
            }
            for t in upper {
                exact_tris.push(t);
                c.tris.push(t.map(|p| p.as_vec3()));
                setup.prim_surface.push((pair, true));
            }
            for far in [false, true] {
                for _ in 0..per {
                    let dist = if far { o } else { 1.0 };
                    let jit = t1 * rng.range(-0.5, 0.5) * half + t2 * rng.range(-0.5, 0.5) * half;
                    let target = center + jit;
                    let origin =
                        target + (n + t1 * rng.range(-0.1, 0.1) + t2 * rng.range(-0.1, 0.1)) * dist;
                    let r = Ray::new(origin.as_vec3(), (target - origin).normalize().as_vec3());
                    probes_todo.push((pair, far, r));
                }
            }
        }
    }
    for (pair, far, r) in probes_todo {
        let intended = closest_f64(&exact_tris, &r);
        c.rays.push(r);
        c.expect.push(Expect::Surface);
        setup.probes.push(Some(SurfaceProbe {
            pair,
            far,
            intended,
        }));
    }
    c.input.exact = false;
    c.any_hit = false;
    c.oracle_budget = c.rays.len();
    c.precision = Some(setup);
    finish_input(&mut c);
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_quick_case_is_well_formed() {
        for c in cases_sized(&CaseOptions::new(Size::Quick)) {
            assert_eq!(c.rays.len(), c.expect.len(), "{}", c.name);
            if c.name != "watertight-real" {
                assert!(!c.tris.is_empty(), "{}", c.name);
                assert!(!c.rays.is_empty(), "{}", c.name);
            }
            if let Some(p) = &c.precision {
                assert_eq!(p.probes.len(), c.rays.len());
                assert_eq!(p.prim_surface.len(), c.tris.len());
            }
        }
    }

    #[test]
    fn instance_cases_are_two_levels_with_every_ray_from_inside() {
        let cases =
            select_cases(&["instances".into()], &CaseOptions::new(Size::Quick)).expect("known");
        assert_eq!(cases.len(), 7);
        for c in &cases {
            let inst = c.instancing.as_ref().expect("two levels");
            let per: usize = inst
                .instances
                .iter()
                .map(|i| inst.meshes[i.mesh as usize].len())
                .sum();
            assert_eq!(c.tris.len(), per, "{}", c.name);
            assert!(
                c.expect.iter().all(|e| *e == Expect::MustHit),
                "{}: {:?}",
                c.name,
                c.notes
            );
        }
        // The mirrored instances keep their winding in the flattened scene: the signed
        // volume of each flattened sphere is positive.
        let m = cases
            .iter()
            .find(|c| c.name == "instances-mirrored")
            .expect("mirrored");
        let n = m.tris.len() / 3;
        for k in 0..3 {
            let vol: f64 = m.tris[k * n..(k + 1) * n]
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|p| p.as_dvec3());
                    a.dot(b.cross(c))
                })
                .sum();
            assert!(vol > 0.0, "instance {k}: {vol}");
        }
    }

    #[test]
    fn selection_by_group_and_name() {
        let c =
            select_cases(&["offset-1e3".into()], &CaseOptions::new(Size::Quick)).expect("known");
        assert_eq!(c.len(), 1);
        let c = select_cases(&["scale".into()], &CaseOptions::new(Size::Quick)).expect("known");
        assert_eq!(c.len(), 6);
        assert!(select_cases(&["nope".into()], &CaseOptions::new(Size::Quick)).is_err());
        let c =
            select_cases(&["scale-limit".into()], &CaseOptions::new(Size::Quick)).expect("known");
        assert!(
            c.iter()
                .all(|c| c.name.starts_with("scale-limit-") && !c.guaranteed)
        );
    }
}
