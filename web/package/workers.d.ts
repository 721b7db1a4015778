// Types of bvhtrace/workers.
import type { Bvh, Hits, TraceOptions } from "./bvhtrace_web.js";

/**
 * Rays on several threads in a browser: module web workers, each with the WebAssembly
 * walk and its own copy of the tree.
 */
export class BvhWorkers {
  /** Starts `count` workers (default: the hardware concurrency), each with a copy of `bvh`. */
  static create(bvh: Bvh, count?: number): Promise<BvhWorkers>;
  /** How many workers trace. */
  readonly count: number;
  /** `Bvh.intersect` over the workers: the same hits, ray for ray. */
  intersect(origins: Float32Array, directions: Float32Array, options?: TraceOptions): Promise<Hits>;
  /** Stops the workers and frees their trees. */
  terminate(): void;
}

/**
 * `new Bvh(positions, indices)` built in a module worker, off the page's thread (call
 * `init()` first): the same tree, bit for bit.
 */
export function buildInWorker(positions: Float32Array, indices?: Uint32Array): Promise<Bvh>;
