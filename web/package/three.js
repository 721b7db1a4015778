// bvhtrace for three.js users: a Bvh over a BufferGeometry, and a Mesh.raycast that asks
// it (the one function a three-mesh-bvh user swaps in). No import of three: the helpers
// use the objects they are given, so any three.js version with BufferGeometry works.
import { Bvh } from "./bvhtrace_web.js";

/** The geometry's positions as a Float32Array of x, y, z per vertex. */
function positionsOf(geometry) {
  const pos = geometry.getAttribute("position");
  if (!pos) throw new Error("bvhtrace: the geometry has no position attribute");
  if (!pos.isInterleavedBufferAttribute && pos.itemSize === 3 && pos.array instanceof Float32Array
      && !pos.normalized) {
    return pos.array.subarray(0, 3 * pos.count);
  }
  const out = new Float32Array(3 * pos.count);
  for (let i = 0; i < pos.count; i++) {
    out[3 * i] = pos.getX(i);
    out[3 * i + 1] = pos.getY(i);
    out[3 * i + 2] = pos.getZ(i);
  }
  return out;
}

/**
 * Builds a Bvh over a three.js BufferGeometry (its position attribute and index, in
 * local space), keeps it as `geometry.bvhtrace` and returns it. Triangle `i` of the
 * geometry is `faceIndex` `i` in every hit.
 */
export function computeBvh(geometry) {
  const index = geometry.getIndex();
  const indices = index ? Uint32Array.from(index.array.subarray(0, index.count)) : undefined;
  disposeBvh(geometry);
  const bvh = new Bvh(positionsOf(geometry), indices);
  geometry.bvhtrace = bvh;
  return bvh;
}

/** Frees `geometry.bvhtrace`, if any. */
export function disposeBvh(geometry) {
  if (geometry.bvhtrace) {
    geometry.bvhtrace.free();
    delete geometry.bvhtrace;
  }
}

/**
 * The closest hit of `raycaster`'s ray on `mesh` (whose geometry has a Bvh, see
 * `computeBvh`), as three.js reports intersections, or null. Both sides of every triangle
 * are hit (three's DoubleSide); `distance` is in world units, within the raycaster's
 * near and far.
 */
export function raycastFirst(mesh, raycaster) {
  const bvh = mesh.geometry.bvhtrace;
  if (!bvh) throw new Error("bvhtrace: the mesh's geometry has no Bvh (call computeBvh first)");
  const inverse = mesh.matrixWorld.clone().invert();
  const local = raycaster.ray.clone().applyMatrix4(inverse);
  const o = local.origin, d = local.direction;
  const hit = bvh.raycastFirst(o.x, o.y, o.z, d.x, d.y, d.z);
  if (!hit) return null;
  const point = o.clone().set(hit.point[0], hit.point[1], hit.point[2]).applyMatrix4(mesh.matrixWorld);
  const distance = raycaster.ray.origin.distanceTo(point);
  if (distance < raycaster.near || distance > raycaster.far) return null;
  const index = mesh.geometry.getIndex();
  const corner = (k) => (index ? index.getX(3 * hit.primitive + k) : 3 * hit.primitive + k);
  return {
    distance,
    point,
    object: mesh,
    faceIndex: hit.primitive,
    face: { a: corner(0), b: corner(1), c: corner(2), materialIndex: 0 },
    barycoord: o.clone().set(1 - hit.u - hit.v, hit.u, hit.v),
  };
}

/**
 * A drop-in `Mesh.prototype.raycast`: `mesh.raycast = acceleratedRaycast` (or on the
 * prototype). Meshes whose geometry has a Bvh report their closest hit (as three-mesh-bvh
 * does with `firstHitOnly`); the others fall back to `fallback`, three's own raycast.
 */
export function acceleratedRaycast(fallback) {
  return function (raycaster, intersects) {
    if (!this.geometry.bvhtrace) return fallback.call(this, raycaster, intersects);
    const hit = raycastFirst(this, raycaster);
    if (hit) intersects.push(hit);
  };
}
