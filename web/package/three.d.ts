// Types of bvhtrace/three: the few three.js shapes the helpers read, so that the package
// needs no three.js types of its own (three's own objects satisfy them).
import type { Bvh } from "./bvhtrace_web.js";

/** What `computeBvh` reads of a three.js BufferGeometry. */
export interface GeometryLike {
  getAttribute(name: "position"): {
    count: number;
    itemSize: number;
    array: ArrayLike<number>;
    normalized?: boolean;
    isInterleavedBufferAttribute?: boolean;
    getX(i: number): number;
    getY(i: number): number;
    getZ(i: number): number;
  } | undefined | null;
  getIndex(): { count: number; array: ArrayLike<number>; getX(i: number): number } | null;
  /** The Bvh `computeBvh` made, if any. */
  bvhtrace?: Bvh;
}

/** A three.js intersection as `raycastFirst` reports it. */
export interface BvhIntersection<Mesh = unknown, Vector3 = unknown> {
  distance: number;
  point: Vector3;
  object: Mesh;
  faceIndex: number;
  face: { a: number; b: number; c: number; materialIndex: number };
  barycoord: Vector3;
}

/**
 * Builds a Bvh over the geometry's positions and index (local space), keeps it as
 * `geometry.bvhtrace` (freeing one made before) and returns it.
 */
export function computeBvh(geometry: GeometryLike): Bvh;

/** Frees `geometry.bvhtrace`, if any. */
export function disposeBvh(geometry: GeometryLike): void;

/**
 * The closest hit of `raycaster`'s ray on `mesh` (both sides of every triangle, within
 * the raycaster's near and far), or null.
 */
export function raycastFirst(mesh: any, raycaster: any): BvhIntersection | null;

/**
 * A drop-in `Mesh.prototype.raycast`: meshes whose geometry has a Bvh report their
 * closest hit, the others go to `fallback` (three's own raycast).
 */
export function acceleratedRaycast(
  fallback: (raycaster: any, intersects: any[]) => void,
): (this: any, raycaster: any, intersects: any[]) => void;
