// Rays on several threads in a browser: module web workers, each with the WebAssembly walk
// and its own copy of the tree (WebAssembly threads that share one memory need a nightly
// Rust build; a copy costs the tree's memory once per worker). Each batch is cut into one
// run of neighbouring rays per worker, and the answers are the one-thread walk's.

import { Bvh } from "./bvhtrace_web.js";

/**
 * `new Bvh(positions, indices)` built in a module worker, so that the page's thread stays
 * free while it builds (the module must be initialised here already, by `init()`): resolves
 * to the same tree, bit for bit, checked as `Bvh.fromBytes` checks it.
 */
export function buildInWorker(positions, indices) {
  return new Promise((resolve, reject) => {
    const w = new Worker(new URL("./worker.js", import.meta.url), { type: "module" });
    w.onmessage = ({ data }) => {
      w.terminate();
      if (data.tree) {
        try {
          resolve(Bvh.fromBytes(data.tree));
        } catch (e) {
          reject(e);
        }
      } else reject(new Error(data.error));
    };
    w.onerror = (e) => {
      w.terminate();
      reject(new Error(`bvhtrace worker: ${e.message}`));
    };
    w.postMessage({ build: { positions, indices } });
  });
}

/** The hits of `parts`, in order, as one `Hits`. */
function join(parts, ms) {
  const count = parts.reduce((n, p) => n + p.count, 0);
  const glue = (key, Type) => {
    const out = new Type(count);
    let at = 0;
    for (const p of parts) {
      out.set(p[key], at);
      at += p.count;
    }
    return out;
  };
  return {
    count,
    hitCount: parts.reduce((n, p) => n + p.hitCount, 0),
    t: glue("t", Float32Array),
    primitive: glue("primitive", Uint32Array),
    u: glue("u", Float32Array),
    v: glue("v", Float32Array),
    backend: `${parts[0]?.backend ?? "wasm"} x ${parts.length} workers`,
    ms,
  };
}

export class BvhWorkers {
  constructor(workers) {
    this.workers = workers;
    this.next = 0;
    this.waiting = new Map();
    for (const w of workers) {
      w.onmessage = ({ data }) => {
        const done = this.waiting.get(data.id);
        this.waiting.delete(data.id);
        if (data.error) done?.reject(new Error(data.error));
        else done?.resolve(data.hits);
      };
    }
  }

  /**
   * Starts `count` workers (default: the browser's hardware concurrency), each loading the
   * module and a copy of `bvh` (through `bvh.toBytes()`); resolves when all are ready.
   */
  static async create(bvh, count = globalThis.navigator?.hardwareConcurrency ?? 2) {
    const tree = bvh.toBytes();
    const workers = await Promise.all(Array.from({ length: Math.max(1, count) }, () =>
      new Promise((resolve, reject) => {
        const w = new Worker(new URL("./worker.js", import.meta.url), { type: "module" });
        w.onmessage = ({ data }) => (data.ready ? resolve(w) : reject(new Error(data.error)));
        w.onerror = (e) => reject(new Error(`bvhtrace worker: ${e.message}`));
        w.postMessage({ tree: tree.slice() });
      })));
    return new BvhWorkers(workers);
  }

  /** How many workers trace. */
  get count() {
    return this.workers.length;
  }

  /**
   * `Bvh.intersect` over the workers: resolves to the same `Hits`, ray for ray, with
   * `backend` naming the workers and `ms` the wall time.
   */
  async intersect(origins, directions, options) {
    const start = performance.now();
    const rays = origins.length / 3;
    if (!Number.isInteger(rays) || origins.length !== directions.length) {
      throw new Error(`${origins.length} origin floats and ${directions.length} direction floats: three per ray, as many of each`);
    }
    const n = this.workers.length;
    const parts = await Promise.all(this.workers.map((w, k) => {
      const [a, b] = [Math.floor((k * rays) / n), Math.floor(((k + 1) * rays) / n)];
      const id = this.next++;
      return new Promise((resolve, reject) => {
        this.waiting.set(id, { resolve, reject });
        const o = origins.slice(3 * a, 3 * b), d = directions.slice(3 * a, 3 * b);
        w.postMessage({ id, origins: o, directions: d, options }, [o.buffer, d.buffer]);
      });
    }));
    return join(parts, performance.now() - start);
  }

  /** Stops the workers and frees their trees. */
  terminate() {
    for (const w of this.workers) w.terminate();
    this.workers = [];
  }
}
