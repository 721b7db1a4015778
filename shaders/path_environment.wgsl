// path_environment.wgsl: the path tracer's environment map (`bvhtrace_path::environment`),
// looked up for a ray that escapes and importance-sampled for next-event estimation.
//
// The host resamples the equirectangular image once into an octahedral map of N x N texels,
// so that this file needs no transcendental function (an equirectangular map would need
// atan2 and acos, which the device and the CPU do not round alike): only + - * /, sqrt,
// abs, floor, min, max, select and integer operations, each in the order the CPU twin
// (`Environment::lookup`, `Environment::sample`) writes them, no `mix`, `dot`, `sign` or
// `normalize` builtin, and no `a + c * (b - a)` for a compiler to turn into a lerp of its
// own rounding. So the twin computes the same bits.
//
// Octahedral map, +Y up: a direction d goes to p = d / (|d.x| + |d.y| + |d.z|) on the
// octahedron. If p.y >= 0 its point of the square [-1, 1]^2 is (u, v) = (p.x, p.z) (the
// upper hemisphere is the middle diamond |u| + |v| <= 1); else (u, v) =
// (+-(1 - |p.z|), +-(1 - |p.x|)) with the signs of p.x and p.z (+ for -0.0). Texel column
// ix = min(floor((u + 1) * N/2), N - 1), row iy likewise from v; texel i = iy * N + ix.
// Back: p = (u, 1 - |u| - |v|, v), folded the same way where its y < 0.
//
// The solid angle of the square's element dA at p (L1 norm 1) is dA / |p|^3, so a
// texel's density over directions is its density over the square times |p|^3.
//
// Words from `e` in `path_data` (declared by path_trace.wgsl): N, N/2 (f32 bits),
// 2/N (f32 bits), then 5 a texel, row by row: red, green, blue (f32 bits), the inclusive
// cumulative distribution (f32 bits, the last exactly 1) and the texel's density over the
// square (f32 bits).

struct PathEnvSample {
    dir: vec3<f32>,
    radiance: vec3<f32>,
    // The density over solid angle of sampling `dir` (0 where the texel is black).
    pdf: f32,
}

fn path_env_word(i: u32) -> f32 {
    return bitcast<f32>(path_data[i]);
}

// Texel `i`'s radiance, and its density at the point of squared length `l2` on the
// octahedron.
fn path_env_texel(e: u32, i: u32, dir: vec3<f32>, l2: f32) -> PathEnvSample {
    let t = e + 3u + 5u * i;
    let radiance = vec3<f32>(path_env_word(t), path_env_word(t + 1u), path_env_word(t + 2u));
    return PathEnvSample(dir, radiance, path_env_word(t + 4u) * (l2 * sqrt(l2)));
}

// The column (or row) of the square's coordinate `c` in [-1, 1].
fn path_env_cell(c: f32, half: f32, n: u32) -> u32 {
    return min(u32(max(floor((c + 1.0) * half), 0.0)), n - 1u);
}

// The environment toward `d` (finite, not zero; need not be unit): its texel's radiance
// and the density with which `path_env_sample` picks `d`. `dir` is `d`.
fn path_env_lookup(e: u32, d: vec3<f32>) -> PathEnvSample {
    let n = path_data[e];
    let half = path_env_word(e + 1u);
    let s = abs(d.x) + abs(d.y) + abs(d.z);
    let p = vec3<f32>(d.x / s, d.y / s, d.z / s);
    var u = p.x;
    var v = p.z;
    if (p.y < 0.0) {
        let fu = 1.0 - abs(p.z);
        let fv = 1.0 - abs(p.x);
        u = select(-fu, fu, p.x >= 0.0);
        v = select(-fv, fv, p.z >= 0.0);
    }
    let i = path_env_cell(v, half, n) * n + path_env_cell(u, half, n);
    return path_env_texel(e, i, d, p.x * p.x + p.y * p.y + p.z * p.z);
}

// A direction drawn with density proportional to the map's luminance (times solid
// angle): texel by `u0` (the first whose cumulative distribution exceeds it), the point in
// it by `u1` and `u2` (uniform over the square's texel), all in [0, 1).
fn path_env_sample(e: u32, u0: f32, u1: f32, u2: f32) -> PathEnvSample {
    let n = path_data[e];
    let step = path_env_word(e + 2u);
    var lo = 0u;
    var hi = n * n - 1u;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        if (path_env_word(e + 6u + 5u * mid) > u0) {
            hi = mid;
        } else {
            lo = mid + 1u;
        }
    }
    let u = -1.0 + (f32(lo % n) + u1) * step;
    let v = -1.0 + (f32(lo / n) + u2) * step;
    let au = abs(u);
    let av = abs(v);
    let y = 1.0 - au - av;
    var x = u;
    var z = v;
    if (y < 0.0) {
        let fx = 1.0 - av;
        let fz = 1.0 - au;
        x = select(-fx, fx, u >= 0.0);
        z = select(-fz, fz, v >= 0.0);
    }
    let l2 = x * x + y * y + z * z;
    let r = 1.0 / sqrt(l2);
    return path_env_texel(e, lo, vec3<f32>(x * r, y * r, z * r), l2);
}
