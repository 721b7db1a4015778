//! Trees larger than one storage binding: an array of the tree in [`BvhStorage::Buffers`]
//! that exceeds the device's largest binding is split into pages, each its own buffer and
//! binding, and the kernels composed for that upload read it through a function that picks
//! the page ([`Pages::specialise`]). A tree that fits one binding composes none of it.
//!
//! Page `p` of the array at binding `b` is bound at `b + PAGE_BINDING_STRIDE * p`; every
//! page but the last holds [`Pages::per_page`] elements, as many as the page's bytes hold
//! ending on a [`PAGE_ALIGN`] boundary.

use crate::error::TraceError;
use crate::plan::DeviceLimits;
use crate::storage::BvhStorage;
use crate::upload::{ArrayRole, DeviceArray};

/// Binding numbers between one page of an array and the next.
pub const PAGE_BINDING_STRIDE: u32 = 8;

/// The most pages one array is split into.
pub const MAX_PAGES: u8 = 16;

/// Bytes every page but the last is a multiple of: the largest storage-buffer offset
/// alignment WebGPU allows, so that the pages may also be ranges of one buffer (the ray
/// queries bind their triangles so).
pub const PAGE_ALIGN: u64 = 256;

/// The arrays a walk reads in storage buffers that may be split: the binding, the WGSL
/// variable, its element type and the element's bytes.
const PAGED_ARRAYS: [(u32, &str, &str, u64); 4] = [
    (0, "bvh_nodes", "BvhNode", 32),
    (0, "bvh_wide_nodes", "BvhWideNode", 80),
    (1, "bvh_triangles", "BvhTriangle", 48),
    (2, "bvh_escapes", "u32", 4),
];

/// `name_1` to `name_15`: the variables of an array's further pages.
macro_rules! page_names {
    ($n:literal) => {
        (
            $n,
            [
                concat!($n, "_1"),
                concat!($n, "_2"),
                concat!($n, "_3"),
                concat!($n, "_4"),
                concat!($n, "_5"),
                concat!($n, "_6"),
                concat!($n, "_7"),
                concat!($n, "_8"),
                concat!($n, "_9"),
                concat!($n, "_10"),
                concat!($n, "_11"),
                concat!($n, "_12"),
                concat!($n, "_13"),
                concat!($n, "_14"),
                concat!($n, "_15"),
            ],
        )
    };
}

/// Each splittable array's variable and its further pages' ([`Pages::specialise`] declares
/// them so).
pub(crate) const PAGE_NAMES: [(&str, [&str; MAX_PAGES as usize - 1]); 4] = [
    page_names!("bvh_nodes"),
    page_names!("bvh_wide_nodes"),
    page_names!("bvh_triangles"),
    page_names!("bvh_escapes"),
];

/// How one layout's arrays of an upload are split: how many pages of `2^log2_bytes` bytes
/// (at most) each holds. [`Pages::ONE`] (the default) splits nothing, whatever the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Pages {
    /// Log2 of a page's largest size in bytes (0 when nothing is split).
    pub log2_bytes: u8,
    /// Pages of the nodes (binding 0).
    pub nodes: u8,
    /// Pages of the triangles (binding 1).
    pub triangles: u8,
    /// Pages of the escape links (binding 2).
    pub escapes: u8,
}

impl Default for Pages {
    fn default() -> Self {
        Pages::ONE
    }
}

impl Pages {
    /// One page per array: nothing split.
    pub const ONE: Pages = Pages {
        log2_bytes: 0,
        nodes: 1,
        triangles: 1,
        escapes: 1,
    };

    /// True when nothing is split.
    pub fn is_one(&self) -> bool {
        *self == Pages::ONE
    }

    /// The largest page size `limits` allow, as a power of two: the largest binding (and
    /// buffer) rounded down.
    pub fn log2_page_bytes(limits: &DeviceLimits) -> u8 {
        let most = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size)
            .max(1);
        (63 - most.leading_zeros()) as u8
    }

    /// Elements of `element_bytes` bytes in one page (every page but the last is full):
    /// as many as the page holds, rounded down so that the page's bytes are a multiple of
    /// [`PAGE_ALIGN`]. The kernels divide by it, a constant (a power of two, as for 48-byte
    /// triangles, would leave up to half of each binding empty: a page more, a binding
    /// more, where WebGPU's default limits allow 8).
    pub fn per_page(&self, element_bytes: u64) -> u64 {
        let step = PAGE_ALIGN / gcd(element_bytes, PAGE_ALIGN);
        let most = (1u64 << self.log2_bytes) / element_bytes;
        (most / step * step).max(step)
    }

    /// Pages of the array at `binding` (1 for an array never split).
    pub fn of_binding(&self, binding: u32) -> u8 {
        match binding {
            0 => self.nodes,
            1 => self.triangles,
            2 => self.escapes,
            _ => 1,
        }
    }

    /// Storage buffers the split arrays add to a kernel beyond one binding each.
    pub fn extra_bindings(&self) -> u32 {
        u32::from(self.nodes + self.triangles + self.escapes) - 3
    }

    /// How `arrays` (one layout's, in `storage`) are split on a device with `limits`:
    /// [`Pages::ONE`] when every array fits one binding or the storage is textures.
    /// [`TraceError::TooLarge`] when an array needs more than [`MAX_PAGES`] pages.
    pub fn plan(
        storage: BvhStorage,
        arrays: &[DeviceArray<'_>],
        limits: &DeviceLimits,
    ) -> Result<Pages, TraceError> {
        let binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let split = arrays
            .iter()
            .any(|a| paged_element(a.role).is_some() && a.bytes.len() as u64 > binding);
        if storage == BvhStorage::Textures || !split {
            return Ok(Pages::ONE);
        }
        let mut pages = Pages {
            log2_bytes: Self::log2_page_bytes(limits),
            ..Pages::ONE
        };
        for a in arrays {
            let Some(element) = paged_element(a.role) else {
                continue;
            };
            let count = (a.bytes.len() as u64 / element).div_ceil(pages.per_page(element));
            if count > u64::from(MAX_PAGES) {
                return Err(TraceError::TooLarge {
                    buffer: a.name(),
                    bytes: a.bytes.len() as u64,
                    limit: u64::from(MAX_PAGES) * pages.per_page(element) * element,
                    limit_name: "MAX_PAGES bindings of max_storage_buffer_binding_size each",
                    storage: Some(storage),
                });
            }
            let count = count.max(1) as u8;
            match a.role.binding() {
                0 => pages.nodes = count,
                1 => pages.triangles = count,
                2 => pages.escapes = count,
                _ => {}
            }
        }
        Ok(pages)
    }

    /// `arrays` split as these pages say: each split array becomes its pages, in order,
    /// each a [`DeviceArray`] of its own with its page number.
    pub fn split<'a>(&self, arrays: Vec<DeviceArray<'a>>) -> Vec<DeviceArray<'a>> {
        if self.is_one() {
            return arrays;
        }
        let mut out = Vec::with_capacity(arrays.len() + self.extra_bindings() as usize);
        for a in arrays {
            match paged_element(a.role) {
                Some(element) if self.of_binding(a.role.binding()) > 1 => {
                    let bytes = (self.per_page(element) * element) as usize;
                    out.extend(a.pages(bytes));
                }
                _ => out.push(a),
            }
        }
        out
    }

    /// `source`, a WGSL file declaring the split arrays, specialised for these pages: each
    /// split array's declaration gains one per further page, every index into it becomes
    /// a call of a function that reads the right page. Unchanged for [`Pages::ONE`].
    pub fn specialise(&self, source: &str) -> String {
        let mut s = source.to_string();
        for (binding, name, ty, element) in PAGED_ARRAYS {
            let count = self.of_binding(binding);
            s = split_array(s, binding, name, ty, self.per_page(element), count, false);
        }
        s
    }

    /// `source` with the `read_write` array `name` of `ty` (`element_bytes` each) at
    /// `binding` split into `count` pages of these pages' size: reads go through
    /// `{name}_at(i)` and whole-element writes (`name[i] = value;`, the only writes
    /// allowed) through `{name}_put(i, value)`. Unchanged for one page. For the programs
    /// that write a tree in place (the device refit).
    pub fn specialise_read_write(
        &self,
        source: &str,
        (binding, name, ty): (u32, &str, &str),
        element_bytes: u64,
        count: u8,
    ) -> String {
        let per = self.per_page(element_bytes);
        split_array(source.to_string(), binding, name, ty, per, count, true)
    }
}

/// `s` with array `name` (at `binding`, of `ty`, `read` or, when `write`, `read_write`)
/// split into `count` pages of `per` elements (see [`Pages::specialise`] and
/// [`Pages::specialise_read_write`]); unchanged for one page or when `s` does not
/// declare it.
fn split_array(
    mut s: String,
    binding: u32,
    name: &str,
    ty: &str,
    per: u64,
    count: u8,
    write: bool,
) -> String {
    let access = if write { "read_write" } else { "read" };
    let decl = format!("var<storage, {access}> {name}: array<{ty}>;");
    if count <= 1 || !s.contains(&decl) {
        return s;
    }
    if write {
        s = write_to_call(&s, name, &format!("{name}_put"));
    }
    s = index_to_call(&s, name, &format!("{name}_at"));
    let mut extra = String::new();
    let (mut cases, mut puts) = (String::new(), String::new());
    for p in 1..u32::from(count) {
        let b = binding + PAGE_BINDING_STRIDE * p;
        extra.push_str(&format!(
            "@group(0) @binding({b}) var<storage, {access}> {name}_{p}: array<{ty}>;\n"
        ));
        cases.push_str(&format!(
            "        case {p}u: {{ return {name}_{p}[i % {per}u]; }}\n"
        ));
        puts.push_str(&format!(
            "        case {p}u: {{ {name}_{p}[i % {per}u] = v; }}\n"
        ));
    }
    extra.push_str(&format!(
        "// Element `i` of `{name}`, split into pages of {per} elements.\n\
         fn {name}_at(i: u32) -> {ty} {{\n    switch i / {per}u {{\n{cases}        \
         default: {{ return {name}[i % {per}u]; }}\n    }}\n}}\n"
    ));
    if write {
        extra.push_str(&format!(
            "fn {name}_put(i: u32, v: {ty}) {{\n    switch i / {per}u {{\n{puts}        \
             default: {{ {name}[i % {per}u] = v; }}\n    }}\n}}\n"
        ));
    }
    let at = s.find(&decl).map_or(s.len(), |i| i + decl.len());
    s.insert_str(at, &format!("\n{extra}"));
    s
}

/// `src` with every whole-element write `name[index] = value;` made `put(index, value);`.
fn write_to_call(src: &str, name: &str, put: &str) -> String {
    rewrite_indexing(src, name, |index, after| {
        let value = (after.trim_start().strip_prefix('=')).filter(|v| !v.starts_with('='))?;
        let stop = value.find(';')?;
        let taken = after.len() - value.len() + stop + 1;
        Some((format!("{put}({index}, {});", value[..stop].trim()), taken))
    })
}

/// `src` with every `name[index]` written `call(index)` (brackets inside `index` kept).
fn index_to_call(src: &str, name: &str, call: &str) -> String {
    rewrite_indexing(src, name, |index, _| Some((format!("{call}({index})"), 0)))
}

/// `src` with each `name[index]` (the whole word `name`, brackets inside `index` kept)
/// replaced as `rewrite(index, what follows the `]`)` says: the text to put instead and
/// how many bytes after the `]` it takes in; `None` leaves that one as it was.
fn rewrite_indexing(
    src: &str,
    name: &str,
    mut rewrite: impl FnMut(&str, &str) -> Option<(String, usize)>,
) -> String {
    let open = format!("{name}[");
    let mut out = String::with_capacity(src.len());
    let mut rest = src;
    while let Some(at) = rest.find(&open) {
        let word_start = at == 0 || {
            let c = rest.as_bytes()[at - 1];
            !(c.is_ascii_alphanumeric() || c == b'_')
        };
        out.push_str(&rest[..at]);
        let inner = &rest[at + open.len()..];
        let done = (word_start.then(|| matching_bracket(inner)).flatten())
            .and_then(|end| Some((end, rewrite(&inner[..end], &inner[end + 1..])?)));
        match done {
            Some((end, (text, taken))) => {
                out.push_str(&text);
                rest = &inner[end + 1 + taken..];
            }
            None => {
                out.push_str(&open);
                rest = inner;
            }
        }
    }
    out.push_str(rest);
    out
}

/// Where the `]` closing an opened `[` is in `s` (which starts after it).
fn matching_bracket(s: &str) -> Option<usize> {
    let mut depth = 1;
    s.char_indices().find_map(|(i, c)| {
        match c {
            '[' => depth += 1,
            ']' => depth -= 1,
            _ => {}
        }
        (depth == 0).then_some(i)
    })
}

/// The greatest common divisor of `a` and `b`.
fn gcd(a: u64, b: u64) -> u64 {
    match b {
        0 => a.max(1),
        _ => gcd(b, a % b),
    }
}

/// The error of a kernel that would bind `needs` storage buffers, a split array's pages
/// among them, on a device allowing `has` per stage; `needed_for` says what needs them.
pub fn too_many_buffers(has: u64, needs: u64, needed_for: &'static str) -> TraceError {
    TraceError::LimitTooLow {
        limit: "max_storage_buffers_per_shader_stage",
        has,
        needs,
        needed_for,
    }
}

/// Checks that a kernel binding `needs` storage buffers fits `limits`
/// ([`too_many_buffers`] otherwise).
pub fn check_storage_buffers(
    needs: u64,
    limits: &DeviceLimits,
    needed_for: &'static str,
) -> Result<(), TraceError> {
    let has = u64::from(limits.max_storage_buffers_per_shader_stage);
    match needs > has {
        true => Err(too_many_buffers(has, needs, needed_for)),
        false => Ok(()),
    }
}

/// Bytes of one element of `role`'s array when it may be split.
fn paged_element(role: ArrayRole) -> Option<u64> {
    match role {
        ArrayRole::Nodes => Some(32),
        ArrayRole::WideNodes => Some(80),
        ArrayRole::Triangles | ArrayRole::WideTriangles => Some(48),
        ArrayRole::Escapes => Some(4),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(binding: u64) -> DeviceLimits {
        DeviceLimits {
            max_storage_buffer_binding_size: binding,
            max_buffer_size: 1 << 40,
            max_compute_workgroups_per_dimension: 65_535,
            min_storage_buffer_offset_alignment: 256,
            max_texture_dimension_2d: 8192,
            max_storage_buffers_per_shader_stage: 8,
        }
    }

    /// Whole-element writes become calls, comparisons and other names untouched.
    #[test]
    fn writes_become_put_calls() {
        let src = "a[f(x[1])] = b[2];\nif (a[0] == c) { a[i + 1u] = m; }\nxa[3] = 4;";
        assert_eq!(
            write_to_call(src, "a", "a_put"),
            "a_put(f(x[1]), b[2]);\nif (a[0] == c) { a_put(i + 1u, m); }\nxa[3] = 4;"
        );
    }

    /// Indexing becomes a call, nested brackets and longer names untouched.
    #[test]
    fn indices_become_calls() {
        let src = "a = bvh_nodes[i].min; b = bvh_nodes[f(x[2])]; c = my_bvh_nodes[3];";
        assert_eq!(
            index_to_call(src, "bvh_nodes", "bvh_nodes_at"),
            "a = bvh_nodes_at(i).min; b = bvh_nodes_at(f(x[2])); c = my_bvh_nodes[3];"
        );
    }

    /// An array over the binding is split into full pages and a last one; the others are
    /// left whole, and textures are never split.
    #[test]
    fn arrays_over_the_binding_are_split_into_pages() {
        use std::borrow::Cow;
        let array = |role, bytes: usize| DeviceArray {
            role,
            bytes: Cow::Owned(vec![0u8; bytes]),
            texel_bytes: None,
            page: 0,
        };
        let arrays = vec![
            array(ArrayRole::Nodes, 32 * 100),
            array(ArrayRole::Triangles, 48 * 10),
        ];
        let l = limits(1024);
        let pages = Pages::plan(BvhStorage::Buffers, &arrays, &l).unwrap();
        assert_eq!((pages.log2_bytes, pages.nodes, pages.triangles), (10, 4, 1));
        assert_eq!((pages.per_page(32), pages.per_page(48)), (32, 16));
        // WebGPU's default 128 MiB binding: 48-byte triangles fill it to within 768 bytes
        // (a power of two would leave a quarter empty), every page 256-byte aligned.
        let webgpu = Pages {
            log2_bytes: 27,
            ..pages
        };
        assert_eq!(webgpu.per_page(48), 2_796_192);
        assert_eq!(webgpu.per_page(32), 1 << 22);
        for element in [4, 8, 16, 32, 48, 64, 80] {
            let bytes = webgpu.per_page(element) * element;
            let step = element * PAGE_ALIGN / gcd(element, PAGE_ALIGN);
            assert!(
                bytes.is_multiple_of(PAGE_ALIGN) && bytes + step > 1 << 27,
                "{element}"
            );
        }
        let split = pages.split(arrays);
        let sizes: Vec<_> = split.iter().map(|a| (a.page, a.bytes.len())).collect();
        assert_eq!(sizes, [(0, 1024), (1, 1024), (2, 1024), (3, 128), (0, 480)]);
        assert_eq!(split[2].binding(), 16);
        let textures = Pages::plan(BvhStorage::Textures, &split, &l).unwrap();
        assert!(textures.is_one());
        let one = Pages::plan(BvhStorage::Buffers, &split[4..], &l).unwrap();
        assert!(one.is_one());
    }

    /// An array needing more than `MAX_PAGES` pages is refused, naming it.
    #[test]
    fn too_many_pages_are_refused() {
        use std::borrow::Cow;
        let a = DeviceArray {
            role: ArrayRole::Triangles,
            bytes: Cow::Owned(vec![0u8; 48 * 1000]),
            texel_bytes: None,
            page: 0,
        };
        match Pages::plan(BvhStorage::Buffers, &[a], &limits(256)) {
            Err(TraceError::TooLarge { buffer, .. }) => assert_eq!(buffer, "triangles"),
            other => panic!("{other:?}"),
        }
    }
}
