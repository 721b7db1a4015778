// bvh_alpha_masks.wgsl: alpha-tested triangles, twin of `bvhtrace_core::masks`
// (`MaskTables::accept`, and the rule in `bvhtrace_core::alpha`). Composed in only when the
// uploaded BVH has masks; the leaf visit (`traverse_common.wgsl`) then asks
// `bvh_alpha_accept` about every candidate that would become the hit.
//
// Binding 5 holds `MaskTables::words`: a `BvhMaskHeader` of word offsets, the instance
// bases (in this layout's instance order), the states, the triangles, the materials and
// the texels, four to a word, little end first.

@group(0) @binding(5) var<storage, read> bvh_masks: array<u32>;

// `masks::MaskHeader`.
struct BvhMaskHeader {
    instance_bases: u32,
    states: u32,
    triangles: u32,
    materials: u32,
    texels: u32,
}

// `masks::MaskTriangle`: the corners' texture coordinates, the material, and the
// micromap (two bits per micro-triangle, read in place by `bvh_micro_state`).
struct BvhMaskTriangle {
    u0: f32,
    v0: f32,
    u1: f32,
    v1: f32,
    u2: f32,
    v2: f32,
    material: u32,
    micro: array<u32, 8>,
}

// `masks::MaskMaterial`.
struct BvhMaskMaterial {
    first_texel: u32,
    width: u32,
    height: u32,
    wrap: u32,
    min_texel: u32,
}

const BVH_MASK_OPAQUE: u32 = 0xffffffffu;
const BVH_MASK_TRANSPARENT: u32 = 0xfffffffeu;
const BVH_NO_MASKS: u32 = 0xffffffffu;
const BVH_MASK_TRIANGLE_WORDS: u32 = 15u;
const BVH_MASK_MATERIAL_WORDS: u32 = 5u;
// `masks::MICRO_CELLS`, the micromap's first word in a triangle, and its states.
const BVH_MICRO_CELLS: u32 = 8u;
const BVH_MICRO_WORD: u32 = 7u;
const BVH_MICRO_TEST: u32 = 0u;
const BVH_MICRO_OPAQUE: u32 = 1u;

// The coordinates and material of the triangle at word `at` (its micromap is read in place).
fn bvh_load_mask_triangle(at: u32) -> BvhMaskTriangle {
    return BvhMaskTriangle(
        bitcast<f32>(bvh_masks[at]),
        bitcast<f32>(bvh_masks[at + 1u]),
        bitcast<f32>(bvh_masks[at + 2u]),
        bitcast<f32>(bvh_masks[at + 3u]),
        bitcast<f32>(bvh_masks[at + 4u]),
        bitcast<f32>(bvh_masks[at + 5u]),
        bvh_masks[at + 6u],
        array<u32, 8>(),
    );
}

// `masks::micro_slot` and `MaskTriangle::micro_state`: the state of the micro-triangle of
// barycentrics `(u, v)` in the micromap of the triangle at word `at`.
fn bvh_micro_state(at: u32, u: f32, v: f32) -> u32 {
    let n = f32(BVH_MICRO_CELLS);
    let last = BVH_MICRO_CELLS - 1u;
    let fu = u * n;
    let fv = v * n;
    let i = min(u32(max(floor(fu), 0.0)), last);
    let j = min(u32(max(floor(fv), 0.0)), last - i);
    let upper = (fu - f32(i)) + (fv - f32(j)) >= 1.0 && i + j < last;
    let slot = 2u * (j * BVH_MICRO_CELLS + i) + select(0u, 1u, upper);
    return (bvh_masks[at + BVH_MICRO_WORD + slot / 16u] >> (2u * (slot % 16u))) & 3u;
}

fn bvh_load_mask_material(at: u32) -> BvhMaskMaterial {
    return BvhMaskMaterial(bvh_masks[at], bvh_masks[at + 1u], bvh_masks[at + 2u], bvh_masks[at + 3u], bvh_masks[at + 4u]);
}

// Whether a candidate at barycentrics `(u, v)` on mesh primitive `prim` counts as a hit
// (`MaskTables::accept`): settled by the triangle's state, or its texel's alpha.
fn bvh_alpha_accept(prim: u32, u: f32, v: f32) -> bool {
    var base = 0u;
    if (BVH_INSTANCED) {
        base = bvh_masks[bvh_masks[0] + bvh_instance_index];
        if (base == BVH_NO_MASKS) {
            return true;
        }
    }
    let state = bvh_masks[bvh_masks[1] + base + prim];
    if (state >= BVH_MASK_TRANSPARENT) {
        return state == BVH_MASK_OPAQUE;
    }
    let at = bvh_masks[2] + BVH_MASK_TRIANGLE_WORDS * state;
    let micro = bvh_micro_state(at, u, v);
    if (micro != BVH_MICRO_TEST) {
        return micro == BVH_MICRO_OPAQUE;
    }
    let t = bvh_load_mask_triangle(at);
    let m = bvh_load_mask_material(bvh_masks[3] + BVH_MASK_MATERIAL_WORDS * t.material);
    // `alpha::interpolate_uv`, in its order of operations.
    let su = (t.u0 + (t.u1 - t.u0) * u) + (t.u2 - t.u0) * v;
    let sv = (t.v0 + (t.v1 - t.v0) * u) + (t.v2 - t.v0) * v;
    let x = bvh_texel_index(su, m.width, m.wrap & 3u);
    let y = bvh_texel_index(sv, m.height, (m.wrap >> 2u) & 3u);
    let i = m.first_texel + y * m.width + x;
    let texel = (bvh_masks[bvh_masks[4] + i / 4u] >> (8u * (i % 4u))) & 0xffu;
    return texel >= m.min_texel;
}
