//! glTF 2.0 loading.
//!
//! The gltf crate parses the JSON into its typed document (`gltf::json::Root`); everything
//! after that is done here, defensively: the GLB container, buffer resolution (GLB `BIN`
//! chunk, external files, `data:` URIs), and every accessor read, whose byte ranges are
//! checked against their buffer view and buffer before a byte is read. Every index the
//! file gives (nodes, meshes, accessors, views, buffers, materials, cameras) is looked up
//! with a check, so a malformed file gives a [`SceneError`], never a panic.

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;

use base64::Engine as _;
use bytemuck::Pod;
use glam::{Mat4, Quat, Vec2, Vec3, Vec4};
use gltf::json::{
    self, Root, accessor::ComponentType, accessor::Type as AccessorType, mesh::Mode,
    mesh::Semantic, validation::Checked,
};

use crate::animation::{self, Animation, AnimationNode, Channel, Morph, NodeTransform, Skin};
use crate::error::{ErrorKind, SceneError};
use crate::{Camera, Instance, Material, Mesh, Scene, glb};

/// Required extensions that do not change how geometry is stored: accepted (materials and
/// textures are not interpreted beyond the base colour factor).
const ACCEPTED_REQUIRED: &[&str] = &[
    "KHR_mesh_quantization",
    "KHR_texture_transform",
    "KHR_texture_basisu",
    "KHR_lights_punctual",
    "KHR_materials_variants",
    "KHR_xmp_json_ld",
    "EXT_texture_webp",
    "EXT_texture_avif",
    "MSFT_texture_dds",
];

/// The most elements an accessor without a buffer view (all zeros) may have.
const MAX_ZERO_ACCESSOR: usize = 1 << 24;

/// Loads a `.gltf` or `.glb` file (binary if it starts with the GLB magic or is named
/// `.glb`). External buffers and images are resolved relative to the file's folder; images
/// are read only for masked materials' alpha, and missing ones only give a warning.
pub fn load_gltf_file(path: &Path) -> Result<Scene, SceneError> {
    let label = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| {
        SceneError::new(
            &label,
            ErrorKind::Io {
                what: "cannot read the file".into(),
                source: e,
            },
        )
    })?;
    load_gltf_slice(&bytes, &label, path.parent())
}

/// Loads glTF from bytes already in memory. `label` names the source in errors (and, if
/// it ends in `.glb`, requires the GLB container); `base_dir` is where external buffer
/// and image URIs are resolved (`None`: only embedded data can be used).
pub fn load_gltf_slice(
    bytes: &[u8],
    label: &str,
    base_dir: Option<&Path>,
) -> Result<Scene, SceneError> {
    let err = |kind| SceneError::new(label, kind);
    let mut warnings = Vec::new();
    let is_glb = bytes.starts_with(glb::MAGIC) || label.to_ascii_lowercase().ends_with(".glb");
    let (json_bytes, bin) = if is_glb {
        let g = glb::parse(bytes).map_err(err)?;
        warnings.extend(g.warnings);
        (g.json, g.bin)
    } else {
        (bytes, None)
    };
    let root = parse_json(json_bytes).map_err(err)?;
    check_required_extensions(&root, &mut warnings).map_err(err)?;
    let buffers = resolve_buffers(&root, bin, base_dir, &mut warnings);
    let name = Path::new(label)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut loader = Loader {
        root: &root,
        buffers,
        warnings,
    };
    let mut scene = loader.load(base_dir).map_err(err)?;
    scene.name = name;
    scene.description = format!("glTF file {label}");
    scene.finish(label)
}

fn parse_json(bytes: &[u8]) -> Result<Root, ErrorKind> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let root: Root =
        json::deserialize::from_slice(bytes).map_err(|e| ErrorKind::Json(e.to_string()))?;
    if !root.asset.version.starts_with('2') {
        return Err(ErrorKind::Invalid(format!(
            "asset.version is {:?}; only glTF 2.0 is supported",
            root.asset.version
        )));
    }
    Ok(root)
}

fn check_required_extensions(root: &Root, warnings: &mut Vec<String>) -> Result<(), ErrorKind> {
    for ext in &root.extensions_required {
        let accepted = ACCEPTED_REQUIRED.contains(&ext.as_str())
            || ext.starts_with("KHR_materials_")
            || ext.starts_with("KHR_texture_");
        if !accepted {
            return Err(ErrorKind::UnsupportedExtension(ext.clone()));
        }
        if ext != "KHR_mesh_quantization" {
            warnings.push(format!(
                "required extension {ext} is ignored (it does not change the geometry)"
            ));
        }
    }
    Ok(())
}

/// Decodes `%XX` escapes in a relative URI (invalid escapes are kept as they are).
pub(crate) fn percent_decode(uri: &str) -> String {
    let b = uri.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let Some(v) = std::str::from_utf8(&b[i + 1..i + 3])
                .ok()
                .and_then(|h| u8::from_str_radix(h, 16).ok())
        {
            out.push(v);
            i += 3;
            continue;
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The payload of a `data:` URI, if it is base64.
pub(crate) fn decode_data_uri(uri: &str) -> Result<Vec<u8>, String> {
    let rest = &uri["data:".len()..];
    let Some(comma) = rest.find(',') else {
        return Err("the data: URI has no ','".into());
    };
    let (header, payload) = (&rest[..comma], &rest[comma + 1..]);
    if !header.ends_with(";base64") {
        return Err(format!(
            "the data: URI is not base64 (media type {header:?})"
        ));
    }
    let cleaned: Cow<str> = if payload.bytes().any(|c| c.is_ascii_whitespace()) {
        Cow::Owned(
            payload
                .chars()
                .filter(|c| !c.is_ascii_whitespace())
                .collect(),
        )
    } else {
        Cow::Borrowed(payload)
    };
    base64::engine::general_purpose::STANDARD
        .decode(cleaned.as_bytes())
        .or_else(|_| {
            base64::engine::general_purpose::STANDARD_NO_PAD
                .decode(cleaned.trim_end_matches('=').as_bytes())
        })
        .map_err(|e| format!("the data: URI is not valid base64: {e}"))
}

/// Reads at most `limit` bytes of a regular file (a URI naming a device or a folder is
/// refused rather than read forever).
pub(crate) fn read_buffer_file(p: &Path, limit: u64) -> Result<Vec<u8>, String> {
    use std::io::Read as _;
    let meta = std::fs::metadata(p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
    if !meta.is_file() {
        return Err(format!("{} is not a regular file", p.display()));
    }
    let f = std::fs::File::open(p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
    let mut out = Vec::with_capacity(meta.len().min(limit) as usize);
    f.take(limit)
        .read_to_end(&mut out)
        .map_err(|e| format!("cannot read {}: {e}", p.display()))?;
    Ok(out)
}

pub(crate) fn is_remote(uri: &str) -> bool {
    uri.contains("://")
}

/// Every buffer's bytes (cut to its declared `byteLength`), or why it is unavailable.
/// Failures are kept, not raised: they become errors only if an accessor reads them.
fn resolve_buffers<'a>(
    root: &Root,
    bin: Option<&'a [u8]>,
    base_dir: Option<&Path>,
    warnings: &mut Vec<String>,
) -> Vec<Result<Cow<'a, [u8]>, String>> {
    root.buffers
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let data: Cow<'a, [u8]> = match b.uri.as_deref() {
                None if i == 0 => match bin {
                    Some(bin) => Cow::Borrowed(bin),
                    None => return Err("has no uri and the file has no GLB BIN chunk".into()),
                },
                None => return Err("has no uri (only buffer 0 may use the GLB BIN chunk)".into()),
                Some(uri) if uri.starts_with("data:") => Cow::Owned(decode_data_uri(uri)?),
                Some(uri) if is_remote(uri) => {
                    return Err(format!("remote URI {uri:?} is not supported"));
                }
                Some(uri) => {
                    let Some(dir) = base_dir else {
                        return Err(format!(
                            "external file {uri:?} cannot be resolved (no base folder)"
                        ));
                    };
                    let p = dir.join(percent_decode(uri));
                    Cow::Owned(read_buffer_file(&p, b.byte_length.0)?)
                }
            };
            let declared = usize::try_from(b.byte_length.0).unwrap_or(usize::MAX);
            if data.len() < declared {
                warnings.push(format!(
                    "buffer {i} has {} bytes but declares byteLength {declared}",
                    data.len()
                ));
                Ok(data)
            } else if data.len() > declared {
                Ok(match data {
                    Cow::Borrowed(s) => Cow::Borrowed(&s[..declared]),
                    Cow::Owned(mut v) => {
                        v.truncate(declared);
                        Cow::Owned(v)
                    }
                })
            } else {
                Ok(data)
            }
        })
        .collect()
}

fn invalid(msg: String) -> ErrorKind {
    ErrorKind::Invalid(msg)
}

/// One triangle primitive, read and checked.
struct Part {
    /// The accessors of POSITION, NORMAL, TEXCOORD_0 and COLOR_0: primitives with the
    /// same key share their vertices.
    key: VertexKey,
    /// The vertex data, or `None` when an earlier primitive of the mesh has the same key.
    vertices: Option<Vertices>,
    tris: Vec<[u32; 3]>,
    material: Option<u32>,
}

/// POSITION, NORMAL, TEXCOORD_0, COLOR_0 and the first morph target's POSITION.
type VertexKey = [Option<usize>; 5];

struct Vertices {
    positions: Vec<Vec3>,
    normals: Option<Vec<Vec3>>,
    texcoords: Option<Vec<Vec2>>,
    colors: Option<Vec<Vec4>>,
    /// JOINTS_0 and WEIGHTS_0, when the primitive has both.
    skin: Option<SkinVertices>,
    /// Each morph target of the primitive.
    targets: Vec<MorphTarget>,
}

/// One morph target of a primitive: its position deltas (zeros when it has none) and its
/// normal deltas, one per vertex.
type MorphTarget = (Vec<Vec3>, Option<Vec<Vec3>>);

/// A mesh's morph targets, merged over its primitives: position deltas target by target
/// (`target * vertices + vertex`), normal deltas likewise (empty when no target has
/// them), and the number of targets.
type MorphVertices = (Vec<Vec3>, Vec<Vec3>, usize);

/// What deforms a mesh's vertices: its skin data and its morph targets, when it has them.
#[derive(Default)]
struct Deforms {
    skin: Option<SkinVertices>,
    morph: Option<MorphVertices>,
}

/// An instance of a mesh with morph targets met in the walk.
struct PendingMorph {
    instance: usize,
    mesh: usize,
    /// The glTF mesh and node, for the static weights.
    gltf_mesh: usize,
    node: usize,
    /// The node's record in the graph.
    rec: usize,
    vertices: MorphVertices,
}

/// Per-vertex joints (indices into the skin's joints) and weights.
type SkinVertices = (Vec<[u16; 4]>, Vec<[f32; 4]>);

/// A skinned instance met in the walk: its skin (glTF index) and its mesh's skin data.
struct PendingSkin {
    instance: usize,
    mesh: usize,
    skin: usize,
    node: usize,
    vertices: SkinVertices,
}

/// The morph targets of a mesh's vertex blocks (in the order their vertices are
/// appended), merged target by target; blocks without a target get zero deltas. `None`
/// when no block has a target.
fn merge_targets<'a>(
    blocks: impl Iterator<Item = &'a Vertices> + Clone,
    nv: usize,
) -> Option<MorphVertices> {
    let targets = blocks.clone().map(|v| v.targets.len()).max().unwrap_or(0);
    if targets == 0 {
        return None;
    }
    let has_normals = (blocks.clone()).any(|v| v.targets.iter().any(|t| t.1.is_some()));
    let (mut positions, mut normals) = (Vec::with_capacity(targets * nv), Vec::new());
    let zeros = |n: usize| std::iter::repeat_n(Vec3::ZERO, n);
    for i in 0..targets {
        for v in blocks.clone() {
            let n = v.positions.len();
            let (p, d) = v
                .targets
                .get(i)
                .map_or((None, None), |(p, d)| (Some(p), d.as_ref()));
            match p {
                Some(p) => positions.extend_from_slice(p),
                None => positions.extend(zeros(n)),
            }
            if has_normals {
                match d {
                    Some(d) => normals.extend_from_slice(d),
                    None => normals.extend(zeros(n)),
                }
            }
        }
    }
    Some((positions, normals, targets))
}

/// A `weights` channel's output (`targets` weights per entry) as one list of values per
/// four targets, for [`animation::Property::Weights`] channels; an output that is not a
/// whole number of entries is an error.
fn weight_chunks(flat: &[[f32; 1]], targets: usize) -> Result<Vec<Vec<Vec4>>, String> {
    let chunks = targets.div_ceil(4);
    if targets == 0 || !flat.len().is_multiple_of(targets) || chunks > usize::from(u16::MAX) {
        return Err(format!(
            "{} weights is not a whole number of entries of {targets} (the mesh's targets)",
            flat.len()
        ));
    }
    Ok((0..chunks)
        .map(|c| {
            (flat.chunks_exact(targets))
                .map(|e| {
                    Vec4::from_array(std::array::from_fn(|k| {
                        e.get(4 * c + k).map_or(0.0, |w| w[0])
                    }))
                })
                .collect()
        })
        .collect())
}

/// The scene graph as the loader walked it (kept only when the file has animations).
#[derive(Default)]
struct Graph {
    /// The visited nodes, parents before children.
    nodes: Vec<AnimationNode>,
    /// glTF node index to index in `nodes`.
    record_of: HashMap<usize, usize>,
    /// For each instance, in order, its node (index in `nodes`).
    instance_nodes: Vec<usize>,
}

impl Graph {
    /// Records glTF node `ni` under `parent`; returns its index in `nodes`.
    fn record(&mut self, ni: usize, node: &json::Node, parent: Option<usize>) -> usize {
        let local = match node.matrix {
            Some(m) => NodeTransform::Matrix(Mat4::from_cols_array(&m)),
            None => NodeTransform::Trs {
                translation: Vec3::from(node.translation.unwrap_or([0.0; 3])),
                rotation: Quat::from_array(node.rotation.map_or([0.0, 0.0, 0.0, 1.0], |q| q.0)),
                scale: Vec3::from(node.scale.unwrap_or([1.0; 3])),
            },
        };
        self.nodes.push(AnimationNode {
            gltf_node: ni,
            parent,
            local,
        });
        let id = self.nodes.len() - 1;
        self.record_of.insert(ni, id);
        id
    }
}

/// An accessor error met while reading an animation, with the animation named first.
fn in_animation(ctx: &str, what: &str, e: ErrorKind) -> ErrorKind {
    let cause = match e {
        ErrorKind::Invalid(s) => s,
        other => other.to_string(),
    };
    invalid(format!("{ctx}: {what}: {cause}"))
}

/// What the loader's walk over the node hierarchy gathers.
#[derive(Default)]
struct Walk {
    meshes: Vec<Mesh>,
    /// glTF mesh index to index in `meshes`, once loaded.
    mesh_map: Vec<Option<usize>>,
    instances: Vec<Instance>,
    materials: Vec<Material>,
    /// The material added for primitives without one, once needed.
    default_material: Option<u32>,
    /// The first usable camera's world transform and vertical field of view in degrees.
    camera_at: Option<(Mat4, f32)>,
    skipped_cameras: usize,
    revisited: usize,
    skinned: usize,
    skins: Vec<PendingSkin>,
    morphs: Vec<PendingMorph>,
    graph: Graph,
}

/// Puts a camera at `world` looking down its -Z, aimed as far as the scene's centre; warns
/// instead when the transform is degenerate.
fn place_camera(scene: &mut Scene, world: Mat4, fov: f32) {
    let eye = world.transform_point3(Vec3::ZERO);
    let fwd = world.transform_vector3(Vec3::NEG_Z).normalize_or_zero();
    if eye.is_finite() && fwd != Vec3::ZERO {
        let (lo, hi) = scene.bounds();
        let d = ((lo + hi) * 0.5 - eye).length();
        let d = if d.is_finite() && d > 0.0 { d } else { 1.0 };
        scene.camera = Some(Camera {
            eye,
            target: eye + fwd * d,
            fov_y_deg: fov,
        });
    } else {
        scene
            .warnings
            .push("the camera's node transform is degenerate; camera skipped".into());
    }
}

struct Loader<'a, 'b> {
    root: &'a Root,
    buffers: Vec<Result<Cow<'b, [u8]>, String>>,
    warnings: Vec<String>,
}

/// How a component type decodes to `f32`.
fn component_size(ct: ComponentType) -> usize {
    match ct {
        ComponentType::I8 | ComponentType::U8 => 1,
        ComponentType::I16 | ComponentType::U16 => 2,
        ComponentType::U32 | ComponentType::F32 => 4,
    }
}

impl<'a, 'b> Loader<'a, 'b> {
    fn accessor(&self, ai: usize) -> Result<&'a json::Accessor, ErrorKind> {
        self.root
            .accessors
            .get(ai)
            .ok_or_else(|| invalid(format!("accessor {ai} does not exist")))
    }

    /// `len` bytes at `offset` in buffer view `vi`, checked against the view and its buffer.
    fn view_bytes(&self, ai: usize, vi: usize, offset: u64, len: u64) -> Result<&[u8], ErrorKind> {
        let view = self.root.buffer_views.get(vi).ok_or_else(|| {
            invalid(format!(
                "accessor {ai} refers to buffer view {vi}, which does not exist"
            ))
        })?;
        let end_in_view = offset.saturating_add(len);
        if end_in_view > view.byte_length.0 {
            return Err(ErrorKind::AccessorOutOfBounds {
                accessor: ai,
                target: format!("buffer view {vi}"),
                needs: end_in_view,
                has: view.byte_length.0,
            });
        }
        let bi = view.buffer.value();
        let buf = match self.buffers.get(bi) {
            None => {
                return Err(invalid(format!(
                    "buffer view {vi} refers to buffer {bi}, which does not exist"
                )));
            }
            Some(Err(reason)) => {
                return Err(ErrorKind::Buffer {
                    buffer: bi,
                    reason: reason.clone(),
                });
            }
            Some(Ok(b)) => b,
        };
        let view_off = view.byte_offset.map_or(0, |o| o.0);
        let start = view_off.saturating_add(offset);
        let end = view_off.saturating_add(end_in_view);
        if end > buf.len() as u64 {
            return Err(ErrorKind::AccessorOutOfBounds {
                accessor: ai,
                target: format!("buffer {bi}"),
                needs: end,
                has: buf.len() as u64,
            });
        }
        // start <= end <= buf.len(), both fit in usize.
        Ok(&buf[start as usize..end as usize])
    }

    /// Reads accessor `ai` element by element (`elem` bytes each) with `decode`, applying
    /// sparse substitution. With `bulk`, tightly packed data is copied in one go (the
    /// element's little-endian bytes must be `T`'s layout).
    fn read_raw<T: Pod>(
        &self,
        ai: usize,
        elem: usize,
        bulk: bool,
        decode: impl Fn(&[u8]) -> T,
    ) -> Result<Vec<T>, ErrorKind> {
        let acc = self.accessor(ai)?;
        let count = usize::try_from(acc.count.0).unwrap_or(usize::MAX);
        let mut out: Vec<T>;
        if let Some(vi) = acc.buffer_view {
            let vi = vi.value();
            let view = self.root.buffer_views.get(vi).ok_or_else(|| {
                invalid(format!(
                    "accessor {ai} refers to buffer view {vi}, which does not exist"
                ))
            })?;
            let stride = match view.byte_stride {
                Some(s) if s.0 != 0 => s.0,
                _ => elem,
            };
            if stride < elem {
                return Err(ErrorKind::Accessor {
                    accessor: ai,
                    reason: format!(
                        "buffer view {vi} has byte stride {stride}, less than the accessor's {elem}-byte elements"
                    ),
                });
            }
            if count == 0 {
                out = Vec::new();
            } else {
                let span = (stride as u64)
                    .saturating_mul(count as u64 - 1)
                    .saturating_add(elem as u64);
                let offset = acc.byte_offset.map_or(0, |o| o.0);
                let bytes = self.view_bytes(ai, vi, offset, span)?;
                if bulk && stride == elem && cfg!(target_endian = "little") {
                    debug_assert_eq!(std::mem::size_of::<T>(), elem);
                    out = vec![T::zeroed(); count];
                    bytemuck::cast_slice_mut::<T, u8>(&mut out)
                        .copy_from_slice(&bytes[..count * elem]);
                } else {
                    out = bytes
                        .chunks(stride)
                        .take(count)
                        .map(|c| decode(&c[..elem]))
                        .collect();
                }
            }
        } else {
            if count > MAX_ZERO_ACCESSOR {
                return Err(ErrorKind::Accessor {
                    accessor: ai,
                    reason: format!(
                        "has no buffer view and {count} elements (at most {MAX_ZERO_ACCESSOR} accepted)"
                    ),
                });
            }
            out = vec![T::zeroed(); count];
        }
        if let Some(sparse) = &acc.sparse {
            self.apply_sparse(ai, sparse, &mut out, elem, &decode)?;
        }
        Ok(out)
    }

    fn apply_sparse<T: Pod>(
        &self,
        ai: usize,
        sparse: &json::accessor::sparse::Sparse,
        out: &mut [T],
        elem: usize,
        decode: &impl Fn(&[u8]) -> T,
    ) -> Result<(), ErrorKind> {
        let n = usize::try_from(sparse.count.0).unwrap_or(usize::MAX);
        if n > out.len() {
            return Err(ErrorKind::Accessor {
                accessor: ai,
                reason: format!(
                    "sparse count {n} is more than the accessor's {} elements",
                    out.len()
                ),
            });
        }
        let isize = match sparse.indices.component_type {
            Checked::Valid(c) => match c.0 {
                ComponentType::U8 => 1,
                ComponentType::U16 => 2,
                ComponentType::U32 => 4,
                other => {
                    return Err(ErrorKind::Accessor {
                        accessor: ai,
                        reason: format!("sparse indices have component type {other:?}"),
                    });
                }
            },
            Checked::Invalid => {
                return Err(ErrorKind::Accessor {
                    accessor: ai,
                    reason: "sparse indices have an invalid component type".into(),
                });
            }
        };
        let idx = self.view_bytes(
            ai,
            sparse.indices.buffer_view.value(),
            sparse.indices.byte_offset.0,
            (n * isize) as u64,
        )?;
        let vals = self.view_bytes(
            ai,
            sparse.values.buffer_view.value(),
            sparse.values.byte_offset.0,
            (n as u64).saturating_mul(elem as u64),
        )?;
        for k in 0..n {
            let b = &idx[k * isize..(k + 1) * isize];
            let i = match isize {
                1 => b[0] as usize,
                2 => u16::from_le_bytes([b[0], b[1]]) as usize,
                _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize,
            };
            let Some(slot) = out.get_mut(i) else {
                return Err(ErrorKind::Accessor {
                    accessor: ai,
                    reason: format!(
                        "sparse index {i} is out of range (the accessor has {} elements)",
                        out.len()
                    ),
                });
            };
            *slot = decode(&vals[k * elem..(k + 1) * elem]);
        }
        Ok(())
    }

    fn accessor_kind(&self, ai: usize) -> Result<(AccessorType, ComponentType, bool), ErrorKind> {
        let acc = self.accessor(ai)?;
        let bad = |what: &str| ErrorKind::Accessor {
            accessor: ai,
            reason: format!("invalid {what}"),
        };
        let ty = match acc.type_ {
            Checked::Valid(t) => t,
            Checked::Invalid => return Err(bad("type")),
        };
        let ct = match acc.component_type {
            Checked::Valid(c) => c.0,
            Checked::Invalid => return Err(bad("componentType")),
        };
        Ok((ty, ct, acc.normalized))
    }

    /// Reads a float vector accessor with `N` components of any component type
    /// (integers converted, normalised when the accessor says so).
    fn read_floats<const N: usize>(&self, ai: usize, what: &str) -> Result<Vec<[f32; N]>, ErrorKind>
    where
        [f32; N]: Pod,
    {
        let (ty, ct, norm) = self.accessor_kind(ai)?;
        if ty.multiplicity() != N || matches!(ty, AccessorType::Mat2) {
            return Err(ErrorKind::Accessor {
                accessor: ai,
                reason: format!("{what} must have {N} components, it is {ty:?}"),
            });
        }
        let sz = component_size(ct);
        let elem = sz * N;
        let conv = |b: &[u8], f: &dyn Fn(&[u8]) -> f32| -> [f32; N] {
            std::array::from_fn(|c| f(&b[c * sz..(c + 1) * sz]))
        };
        match ct {
            ComponentType::F32 => self.read_raw(ai, elem, true, |b| {
                std::array::from_fn(|c| {
                    f32::from_le_bytes([b[4 * c], b[4 * c + 1], b[4 * c + 2], b[4 * c + 3]])
                })
            }),
            ComponentType::U8 => self.read_raw(ai, elem, false, |b| {
                conv(b, &|x| {
                    if norm {
                        x[0] as f32 / 255.0
                    } else {
                        x[0] as f32
                    }
                })
            }),
            ComponentType::I8 => self.read_raw(ai, elem, false, |b| {
                conv(b, &|x| {
                    let v = x[0] as i8 as f32;
                    if norm { (v / 127.0).max(-1.0) } else { v }
                })
            }),
            ComponentType::U16 => self.read_raw(ai, elem, false, |b| {
                conv(b, &|x| {
                    let v = u16::from_le_bytes([x[0], x[1]]) as f32;
                    if norm { v / 65535.0 } else { v }
                })
            }),
            ComponentType::I16 => self.read_raw(ai, elem, false, |b| {
                conv(b, &|x| {
                    let v = i16::from_le_bytes([x[0], x[1]]) as f32;
                    if norm { (v / 32767.0).max(-1.0) } else { v }
                })
            }),
            ComponentType::U32 => self.read_raw(ai, elem, false, |b| {
                conv(b, &|x| {
                    let v = u32::from_le_bytes([x[0], x[1], x[2], x[3]]);
                    if norm {
                        (v as f64 / u32::MAX as f64) as f32
                    } else {
                        v as f32
                    }
                })
            }),
        }
    }

    /// Reads an index accessor (`SCALAR`, unsigned 8, 16 or 32 bits).
    fn read_indices(&self, ai: usize) -> Result<Vec<u32>, ErrorKind> {
        let (ty, ct, _) = self.accessor_kind(ai)?;
        if ty != AccessorType::Scalar {
            return Err(ErrorKind::Accessor {
                accessor: ai,
                reason: format!("indices must be SCALAR, they are {ty:?}"),
            });
        }
        match ct {
            ComponentType::U8 => self.read_raw(ai, 1, false, |b| b[0] as u32),
            ComponentType::U16 => {
                self.read_raw(ai, 2, false, |b| u16::from_le_bytes([b[0], b[1]]) as u32)
            }
            ComponentType::U32 => self.read_raw(ai, 4, true, |b| {
                u32::from_le_bytes([b[0], b[1], b[2], b[3]])
            }),
            other => Err(ErrorKind::Accessor {
                accessor: ai,
                reason: format!("indices must be unsigned integers, they are {other:?}"),
            }),
        }
    }

    /// Reads an optional attribute: errors in its data are errors, but a wrong type or
    /// count only drops the attribute with a warning.
    fn optional<const N: usize>(
        &mut self,
        prim: &json::mesh::Primitive,
        sem: Semantic,
        name: &str,
        nv: usize,
        ctx: &str,
    ) -> Result<Option<Vec<[f32; N]>>, ErrorKind>
    where
        [f32; N]: Pod,
    {
        let Some(ai) = prim.attributes.get(&Checked::Valid(sem)) else {
            return Ok(None);
        };
        let ai = ai.value();
        let (ty, _, _) = self.accessor_kind(ai)?;
        if ty.multiplicity() != N || matches!(ty, AccessorType::Mat2) {
            self.warnings.push(format!(
                "{ctx}: {name} accessor {ai} is {ty:?}, expected {N} components; ignored"
            ));
            return Ok(None);
        }
        let v = self.read_floats::<N>(ai, name)?;
        if v.len() != nv {
            self.warnings.push(format!(
                "{ctx}: {name} has {} elements but POSITION has {nv}; ignored",
                v.len()
            ));
            return Ok(None);
        }
        Ok(Some(v))
    }

    #[allow(clippy::too_many_arguments)]
    fn load_part(
        &mut self,
        mi: usize,
        pi: usize,
        prim: &json::mesh::Primitive,
        has_materials: bool,
        default_material: &mut Option<u32>,
        materials: &mut Vec<Material>,
        seen: &HashMap<VertexKey, usize>,
    ) -> Result<Option<Part>, ErrorKind> {
        let ctx = format!("mesh {mi} primitive {pi}");
        let mode = match prim.mode {
            Checked::Valid(m) => m,
            Checked::Invalid => {
                self.warnings.push(format!("{ctx}: invalid mode; skipped"));
                return Ok(None);
            }
        };
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            self.warnings
                .push(format!("{ctx}: mode {mode:?} is not triangles; skipped"));
            return Ok(None);
        }
        let Some(pos) = prim.attributes.get(&Checked::Valid(Semantic::Positions)) else {
            self.warnings
                .push(format!("{ctx}: no POSITION attribute; skipped"));
            return Ok(None);
        };
        let attr = |sem: Semantic| prim.attributes.get(&Checked::Valid(sem)).map(|a| a.value());
        let key: VertexKey = [
            Some(pos.value()),
            attr(Semantic::Normals),
            attr(Semantic::TexCoords(0)),
            attr(Semantic::Colors(0)),
            (prim.targets.iter().flatten().next()).and_then(|t| t.positions.map(|a| a.value())),
        ];
        let (vertices, nv) = match seen.get(&key) {
            Some(&nv) => (None, nv),
            None => {
                let v = self.read_vertices(mi, pi, prim, pos.value(), &ctx)?;
                let nv = v.positions.len();
                (Some(v), nv)
            }
        };
        let tris: Vec<[u32; 3]> = match prim.indices {
            Some(ai) => {
                let idx = self.read_indices(ai.value())?;
                self.assemble(mode, &idx, &ctx)
            }
            None => {
                let idx: Vec<u32> = (0..nv as u32).collect();
                self.assemble(mode, &idx, &ctx)
            }
        };
        for (t, tri) in tris.iter().enumerate() {
            if let Some(&i) = tri.iter().find(|&&i| i as usize >= nv) {
                return Err(ErrorKind::IndexOutOfRange {
                    mesh: mi,
                    primitive: pi,
                    triangle: t,
                    index: i,
                    vertices: nv,
                });
            }
        }
        let material = if has_materials {
            match prim.material.map(|m| m.value()) {
                Some(m) if m < self.root.materials.len() => Some(m as u32),
                other => {
                    if let Some(m) = other {
                        self.warnings.push(format!(
                            "{ctx}: material {m} does not exist; the default material is used"
                        ));
                    }
                    Some(*default_material.get_or_insert_with(|| {
                        materials.push(Material::opaque("default", Vec4::ONE));
                        (materials.len() - 1) as u32
                    }))
                }
            }
        } else {
            None
        };
        Ok(Some(Part {
            key,
            vertices,
            tris,
            material,
        }))
    }

    /// Reads a primitive's vertex attributes (POSITION must be finite; the optional ones
    /// are dropped with a warning when their type or count is wrong).
    fn read_vertices(
        &mut self,
        mi: usize,
        pi: usize,
        prim: &json::mesh::Primitive,
        pos: usize,
        ctx: &str,
    ) -> Result<Vertices, ErrorKind> {
        let raw = self.read_floats::<3>(pos, "POSITION")?;
        if let Some(v) = raw.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
            return Err(ErrorKind::NonFinitePosition {
                mesh: mi,
                primitive: pi,
                vertex: v,
                value: raw[v],
            });
        }
        let positions: Vec<Vec3> = bytemuck::cast_vec(raw);
        let nv = positions.len();
        if nv > u32::MAX as usize {
            return Err(ErrorKind::TooLarge(format!("{ctx}: {nv} vertices")));
        }
        let normals = self
            .optional::<3>(prim, Semantic::Normals, "NORMAL", nv, ctx)?
            .map(|v| {
                let mut n: Vec<Vec3> = bytemuck::cast_vec(v);
                let mut fixed = false;
                for x in &mut n {
                    let l2 = x.length_squared();
                    let u = if !x.is_finite() {
                        Vec3::ZERO
                    } else if (l2 - 1.0).abs() <= 1e-5 {
                        *x
                    } else {
                        x.normalize_or_zero()
                    };
                    if u == Vec3::ZERO {
                        fixed = true;
                        *x = Vec3::Y;
                    } else {
                        *x = u;
                    }
                }
                if fixed {
                    self.warnings.push(format!(
                        "{ctx}: some normals are zero or not finite; replaced by +Y"
                    ));
                }
                n
            });
        let texcoords = self
            .optional::<2>(prim, Semantic::TexCoords(0), "TEXCOORD_0", nv, ctx)?
            .map(|v| {
                v.into_iter()
                    .map(|t| {
                        let t = Vec2::from(t);
                        if t.is_finite() { t } else { Vec2::ZERO }
                    })
                    .collect()
            });
        let colors = match prim.attributes.get(&Checked::Valid(Semantic::Colors(0))) {
            None => None,
            Some(ai) => match self.accessor_kind(ai.value())?.0 {
                AccessorType::Vec3 => self
                    .optional::<3>(prim, Semantic::Colors(0), "COLOR_0", nv, ctx)?
                    .map(|v| v.into_iter().map(|c| Vec3::from(c).extend(1.0)).collect()),
                _ => self
                    .optional::<4>(prim, Semantic::Colors(0), "COLOR_0", nv, ctx)?
                    .map(|v| v.into_iter().map(Vec4::from).collect()),
            },
        }
        .map(|v: Vec<Vec4>| {
            v.into_iter()
                .map(|c| if c.is_finite() { c } else { Vec4::ONE })
                .collect()
        });
        let joints = self.optional::<4>(prim, Semantic::Joints(0), "JOINTS_0", nv, ctx)?;
        let weights = self.optional::<4>(prim, Semantic::Weights(0), "WEIGHTS_0", nv, ctx)?;
        let skin = joints.zip(weights).map(|(j, w)| {
            let joints = j.into_iter().map(|q| q.map(|x| x as u16)).collect();
            let weights = w
                .into_iter()
                .map(|w| {
                    if w.iter().all(|x| x.is_finite()) {
                        w
                    } else {
                        [0.0; 4]
                    }
                })
                .collect();
            (joints, weights)
        });
        let targets = self.read_targets(prim, nv, ctx)?;
        Ok(Vertices {
            positions,
            normals,
            texcoords,
            colors,
            skin,
            targets,
        })
    }

    /// A primitive's morph targets: position deltas (zeros where a target has none) and
    /// normal deltas, one per vertex; deltas that are not finite are an error naming the
    /// target.
    fn read_targets(
        &mut self,
        prim: &json::mesh::Primitive,
        nv: usize,
        ctx: &str,
    ) -> Result<Vec<MorphTarget>, ErrorKind> {
        let mut out = Vec::new();
        for (i, t) in prim.targets.iter().flatten().enumerate() {
            let read = |a: Option<json::Index<json::Accessor>>, what: &str| {
                let Some(a) = a else {
                    return Ok(None);
                };
                let name = format!("morph target {i} {what}");
                let v: Vec<Vec3> = bytemuck::cast_vec(self.read_floats::<3>(a.value(), &name)?);
                if v.len() != nv {
                    return Err(invalid(format!(
                        "{ctx}: {name} has {} elements but POSITION has {nv}",
                        v.len()
                    )));
                }
                if let Some(k) = v.iter().position(|d| !d.is_finite()) {
                    return Err(invalid(format!(
                        "{ctx}: {name}: delta {k} is not finite ({})",
                        v[k]
                    )));
                }
                Ok(Some(v))
            };
            let positions = read(t.positions, "POSITION")?;
            let normals = read(t.normals, "NORMAL")?;
            out.push((positions.unwrap_or_else(|| vec![Vec3::ZERO; nv]), normals));
        }
        Ok(out)
    }

    /// Triangles from a primitive's index list, by mode (glTF spec, section 3.7.2.1).
    fn assemble(&mut self, mode: Mode, idx: &[u32], ctx: &str) -> Vec<[u32; 3]> {
        match mode {
            Mode::TriangleStrip => (0..idx.len().saturating_sub(2))
                .map(|i| {
                    if i % 2 == 0 {
                        [idx[i], idx[i + 1], idx[i + 2]]
                    } else {
                        [idx[i], idx[i + 2], idx[i + 1]]
                    }
                })
                .collect(),
            Mode::TriangleFan => (0..idx.len().saturating_sub(2))
                .map(|i| [idx[i + 1], idx[i + 2], idx[0]])
                .collect(),
            _ => {
                if !idx.len().is_multiple_of(3) {
                    self.warnings.push(format!(
                        "{ctx}: {} indices is not a multiple of 3; the last {} ignored",
                        idx.len(),
                        idx.len() % 3
                    ));
                }
                idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
            }
        }
    }

    fn load_mesh(
        &mut self,
        mi: usize,
        default_material: &mut Option<u32>,
        materials: &mut Vec<Material>,
    ) -> Result<(Mesh, Deforms), ErrorKind> {
        let root = self.root;
        let mesh = root
            .meshes
            .get(mi)
            .ok_or_else(|| invalid(format!("mesh {mi} does not exist")))?;
        let has_materials = !root.materials.is_empty();
        let mut parts = Vec::new();
        let mut seen: HashMap<VertexKey, usize> = HashMap::new();
        for (pi, prim) in mesh.primitives.iter().enumerate() {
            if let Some(p) = self.load_part(
                mi,
                pi,
                prim,
                has_materials,
                default_material,
                materials,
                &seen,
            )? {
                if let Some(v) = &p.vertices {
                    seen.insert(p.key, v.positions.len());
                }
                parts.push(p);
            }
        }
        let verts = || parts.iter().filter_map(|p| p.vertices.as_ref());
        let nv: usize = verts().map(|v| v.positions.len()).sum();
        if nv > u32::MAX as usize {
            return Err(ErrorKind::TooLarge(format!("mesh {mi}: {nv} vertices")));
        }
        let nt: usize = parts.iter().map(|p| p.tris.len()).sum();
        let any_n = verts().any(|v| v.normals.is_some());
        let any_t = verts().any(|v| v.texcoords.is_some());
        let any_c = verts().any(|v| v.colors.is_some());
        let any_m = parts.iter().any(|p| p.material.is_some());
        // Skin data only when every primitive's vertices have it.
        let mut skin: Option<SkinVertices> = verts()
            .all(|v| v.skin.is_some())
            .then(|| (Vec::new(), Vec::new()));
        let morph = merge_targets(verts(), nv);
        let mut out = Mesh {
            name: mesh.name.clone().unwrap_or_default(),
            positions: Vec::with_capacity(nv),
            indices: Vec::with_capacity(nt),
            ..Mesh::default()
        };
        let mut bases: HashMap<VertexKey, u32> = HashMap::new();
        for p in parts {
            let base = match p.vertices {
                None => bases.get(&p.key).copied().unwrap_or(0),
                Some(v) => {
                    let base = out.positions.len() as u32;
                    bases.insert(p.key, base);
                    let n = v.positions.len();
                    if any_n {
                        match v.normals {
                            Some(x) => out.normals.extend(x),
                            None => out
                                .normals
                                .extend(crate::vertex_normals(&v.positions, &p.tris)),
                        }
                    }
                    if any_t {
                        match v.texcoords {
                            Some(x) => out.texcoords.extend(x),
                            None => out.texcoords.extend(std::iter::repeat_n(Vec2::ZERO, n)),
                        }
                    }
                    if any_c {
                        match v.colors {
                            Some(x) => out.colors.extend(x),
                            None => out.colors.extend(std::iter::repeat_n(Vec4::ONE, n)),
                        }
                    }
                    if let (Some((js, ws)), Some((j, w))) = (skin.as_mut(), v.skin) {
                        js.extend(j);
                        ws.extend(w);
                    }
                    if out.positions.is_empty() {
                        out.positions = v.positions;
                    } else {
                        out.positions.extend(v.positions);
                    }
                    base
                }
            };
            if any_m {
                out.materials
                    .extend(std::iter::repeat_n(p.material.unwrap_or(0), p.tris.len()));
            }
            if base == 0 && out.indices.is_empty() {
                out.indices = p.tris;
            } else {
                out.indices
                    .extend(p.tris.iter().map(|t| t.map(|i| i + base)));
            }
        }
        Ok((out, Deforms { skin, morph }))
    }

    fn node_matrix(node: &json::Node) -> Result<Mat4, String> {
        if let Some(m) = node.matrix {
            let mat = Mat4::from_cols_array(&m);
            if !mat.is_finite() {
                return Err(format!("its matrix is not finite ({m:?})"));
            }
            return Ok(mat);
        }
        let t = Vec3::from(node.translation.unwrap_or([0.0; 3]));
        let s = Vec3::from(node.scale.unwrap_or([1.0; 3]));
        let r = node.rotation.map_or([0.0, 0.0, 0.0, 1.0], |q| q.0);
        if !t.is_finite() {
            return Err(format!("its translation is not finite ({t})"));
        }
        if !s.is_finite() {
            return Err(format!("its scale is not finite ({s})"));
        }
        let q = Vec4::from(r);
        let len = q.length();
        if !(len.is_finite() && len > 1e-6) {
            return Err(format!("its rotation {r:?} is not a unit quaternion"));
        }
        // The same arithmetic as animated nodes use, so that both agree bit for bit.
        Ok(animation::compose_trs(t, q, s))
    }

    fn load(&mut self, base_dir: Option<&Path>) -> Result<Scene, ErrorKind> {
        let root = self.root;
        let loaded = self.materials(base_dir);
        let mut walk = Walk {
            materials: loaded.materials,
            mesh_map: vec![None; root.meshes.len()],
            ..Walk::default()
        };
        let roots = self.root_nodes()?;
        // With animations, the walk is recorded: each visited node (parent links and
        // static transform) and the node of each instance.
        let morphs = (root.meshes.iter().flat_map(|m| &m.primitives)).any(|p| p.targets.is_some());
        let track = !root.animations.is_empty() || !root.skins.is_empty() || morphs;
        self.walk_nodes(&mut walk, &roots, track)?;
        if root.nodes.is_empty() && !root.meshes.is_empty() {
            self.place_meshes_once(&mut walk)?;
        }
        self.warn_walk(&walk);
        self.warn_missing_images(base_dir);
        let animation = if track {
            let n = walk.instances.len();
            let skins =
                self.load_skins(&walk.graph, std::mem::take(&mut walk.skins), &walk.meshes)?;
            let morphs = self.load_morphs(std::mem::take(&mut walk.morphs), &walk.meshes);
            self.load_animations(walk.graph, skins, morphs)?
                .filter(|a| a.instance_nodes.len() == n)
        } else {
            None
        };

        let mut scene = Scene {
            meshes: walk.meshes,
            instances: walk.instances,
            materials: walk.materials,
            alpha_textures: loaded.alpha_textures,
            textures: loaded.textures,
            warnings: std::mem::take(&mut self.warnings),
            animation,
            ..Scene::default()
        };
        if scene.triangle_count() == 0 {
            let prims: usize = root.meshes.iter().map(|m| m.primitives.len()).sum();
            return Err(ErrorKind::NoTriangles(format!(
                " ({} instance(s) of {} mesh(es) with {} primitive(s) in the file)",
                scene.instances.len(),
                root.meshes.len(),
                prims
            )));
        }
        scene.unify_attributes();
        // Skinned and morphed meshes in their static pose.
        scene.apply_deformations(None);
        if let Some((world, fov)) = walk.camera_at {
            place_camera(&mut scene, world, fov);
        }
        Ok(scene)
    }

    /// The file's materials, named by index when they have no name (a base colour that
    /// is not finite becomes white), and the textures they sample.
    fn materials(&mut self, base_dir: Option<&Path>) -> crate::materials::Loaded {
        let view = |vi: usize| self.whole_view(vi);
        let src = crate::materials::ImageSource {
            root: self.root,
            base_dir,
            view: &view,
        };
        let mut warnings = Vec::new();
        let out = crate::materials::load(&src, &mut warnings);
        self.warnings.extend(warnings);
        out
    }

    /// Buffer view `vi`'s bytes (an image's), or why they cannot be read.
    fn whole_view(&self, vi: usize) -> Result<Vec<u8>, String> {
        let view = (self.root.buffer_views.get(vi))
            .ok_or_else(|| format!("buffer view {vi} does not exist"))?;
        let bi = view.buffer.value();
        let buf = match self.buffers.get(bi) {
            None => return Err(format!("buffer view {vi}'s buffer {bi} does not exist")),
            Some(Err(reason)) => return Err(format!("buffer {bi}: {reason}")),
            Some(Ok(b)) => b,
        };
        let start = view.byte_offset.map_or(0, |o| o.0);
        let end = start.saturating_add(view.byte_length.0);
        (buf.get(start as usize..end as usize))
            .map(<[u8]>::to_vec)
            .ok_or_else(|| {
                format!(
                    "buffer view {vi} runs past buffer {bi} ({} bytes)",
                    buf.len()
                )
            })
    }

    /// The nodes to start from: the default scene's, else the first scene's, else
    /// every node that is nobody's child.
    fn root_nodes(&self) -> Result<Vec<usize>, ErrorKind> {
        let root = self.root;
        let first = if root.scenes.is_empty() {
            None
        } else {
            Some(0)
        };
        Ok(match root.scene.map(|s| s.value()).or(first) {
            Some(si) => root
                .scenes
                .get(si)
                .ok_or_else(|| invalid(format!("the default scene {si} does not exist")))?
                .nodes
                .iter()
                .map(|n| n.value())
                .collect(),
            None => {
                let mut is_child = vec![false; root.nodes.len()];
                for n in &root.nodes {
                    for c in n.children.iter().flatten() {
                        if let Some(f) = is_child.get_mut(c.value()) {
                            *f = true;
                        }
                    }
                }
                (0..root.nodes.len()).filter(|&i| !is_child[i]).collect()
            }
        })
    }

    /// Walks the hierarchy depth first from `roots`, visiting each node once: places an
    /// instance for each mesh node and takes the first usable camera.
    fn walk_nodes(
        &mut self,
        walk: &mut Walk,
        roots: &[usize],
        track: bool,
    ) -> Result<(), ErrorKind> {
        let root = self.root;
        let mut visited = vec![false; root.nodes.len()];
        let mut stack: Vec<(usize, Mat4, Option<usize>)> = roots
            .iter()
            .rev()
            .map(|&n| (n, Mat4::IDENTITY, None))
            .collect();
        while let Some((ni, parent, parent_rec)) = stack.pop() {
            let node = root
                .nodes
                .get(ni)
                .ok_or_else(|| invalid(format!("node {ni} does not exist")))?;
            if visited[ni] {
                walk.revisited += 1;
                continue;
            }
            visited[ni] = true;
            let world = Self::world_matrix(ni, node, parent)?;
            let rec = track.then(|| walk.graph.record(ni, node, parent_rec));
            if let Some(m) = node.mesh {
                self.place_instance(walk, ni, node, m.value(), world, rec)?;
            }
            if let Some(c) = node.camera {
                self.note_camera(walk, ni, c.value(), world)?;
            }
            for ch in node.children.iter().flatten().rev() {
                stack.push((ch.value(), world, rec));
            }
        }
        Ok(())
    }

    /// Node `ni`'s world transform under `parent`; an error when it is not finite.
    fn world_matrix(ni: usize, node: &json::Node, parent: Mat4) -> Result<Mat4, ErrorKind> {
        let local =
            Self::node_matrix(node).map_err(|reason| ErrorKind::Node { node: ni, reason })?;
        let world = parent * local;
        if !world.is_finite() {
            return Err(ErrorKind::Node {
                node: ni,
                reason: "its world transform is not finite (the transforms overflow f32)".into(),
            });
        }
        Ok(world)
    }

    /// Places an instance of mesh `m` (of node `ni`, recorded as `rec`) at `world`,
    /// loading the mesh on its first use.
    fn place_instance(
        &mut self,
        walk: &mut Walk,
        ni: usize,
        node: &json::Node,
        m: usize,
        world: Mat4,
        rec: Option<usize>,
    ) -> Result<(), ErrorKind> {
        let slot = walk.mesh_map.get_mut(m).ok_or_else(|| {
            invalid(format!(
                "node {ni} refers to mesh {m}, which does not exist"
            ))
        })?;
        // A skinned or morphed instance gets a mesh of its own: its joints and weights
        // rewrite the positions.
        let skinned = node.skin.map(|s| s.value());
        let morphed = (self.root.meshes.get(m))
            .is_some_and(|mesh| mesh.primitives.iter().any(|p| p.targets.is_some()));
        let id = match (*slot, skinned.is_some() || morphed) {
            (Some(id), false) => id,
            _ => {
                let (mesh, deforms) =
                    self.load_mesh(m, &mut walk.default_material, &mut walk.materials)?;
                walk.meshes.push(mesh);
                let id = walk.meshes.len() - 1;
                let instance = walk.instances.len();
                match (skinned, deforms.skin) {
                    (None, _) if !morphed => walk.mesh_map[m] = Some(id),
                    (None, _) => {}
                    (Some(skin), Some(vertices)) if rec.is_some() => walk.skins.push(PendingSkin {
                        instance,
                        mesh: id,
                        skin,
                        node: ni,
                        vertices,
                    }),
                    (Some(_), _) => walk.skinned += 1,
                }
                if let (Some(vertices), Some(rec)) = (deforms.morph, rec) {
                    walk.morphs.push(PendingMorph {
                        instance,
                        mesh: id,
                        gltf_mesh: m,
                        node: ni,
                        rec,
                        vertices,
                    });
                }
                id
            }
        };
        walk.instances.push(Instance {
            mesh: id,
            transform: world,
        });
        walk.graph.instance_nodes.extend(rec);
        Ok(())
    }

    /// Takes camera `c` of node `ni` at `world` when it is the first and a perspective
    /// camera with a usable field of view; counts it as skipped when not.
    fn note_camera(
        &self,
        walk: &mut Walk,
        ni: usize,
        c: usize,
        world: Mat4,
    ) -> Result<(), ErrorKind> {
        let cam = self.root.cameras.get(c).ok_or_else(|| {
            invalid(format!(
                "node {ni} refers to camera {c}, which does not exist"
            ))
        })?;
        match (&cam.perspective, walk.camera_at) {
            (Some(p), None)
                if p.yfov.is_finite() && p.yfov > 0.0 && p.yfov < std::f32::consts::PI =>
            {
                walk.camera_at = Some((world, p.yfov.to_degrees()));
            }
            (_, None) => walk.skipped_cameras += 1,
            _ => {}
        }
        Ok(())
    }

    /// For a file without nodes: places each mesh once, untransformed.
    fn place_meshes_once(&mut self, walk: &mut Walk) -> Result<(), ErrorKind> {
        self.warnings
            .push("the file has no nodes: each mesh is placed once, untransformed".into());
        for m in 0..self.root.meshes.len() {
            let (mesh, _) = self.load_mesh(m, &mut walk.default_material, &mut walk.materials)?;
            walk.meshes.push(mesh);
            walk.instances.push(Instance {
                mesh: walk.meshes.len() - 1,
                transform: Mat4::IDENTITY,
            });
        }
        Ok(())
    }

    /// Warns of what the walk skipped: revisited nodes, skins and cameras.
    fn warn_walk(&mut self, walk: &Walk) {
        let (revisited, skinned, skipped_cameras) =
            (walk.revisited, walk.skinned, walk.skipped_cameras);
        if revisited > 0 {
            self.warnings.push(format!(
                "{revisited} node visit(s) skipped: a node has several parents or the hierarchy has a cycle"
            ));
        }
        if skinned > 0 {
            self.warnings.push(format!(
                "{skinned} skinned mesh instance(s) without JOINTS_0 and WEIGHTS_0 on every primitive are placed by their node transform"
            ));
        }
        if skipped_cameras > 0 {
            self.warnings.push(format!(
                "{skipped_cameras} camera(s) skipped (orthographic, or an invalid field of view)"
            ));
        }
    }

    /// The skins of the skinned instances met in the walk: joints as nodes of `graph`, the
    /// inverse bind matrices (identity when the file has none). A skin whose joint is
    /// outside the loaded scene graph, or a vertex naming a joint it lacks, is an error
    /// naming the skin.
    fn load_skins(
        &mut self,
        graph: &Graph,
        pending: Vec<PendingSkin>,
        meshes: &[Mesh],
    ) -> Result<Vec<Skin>, ErrorKind> {
        let root = self.root;
        let mut out = Vec::new();
        for p in pending {
            let bad =
                |reason: String| invalid(format!("skin {} (node {}): {reason}", p.skin, p.node));
            let skin = root
                .skins
                .get(p.skin)
                .ok_or_else(|| bad("does not exist".into()))?;
            let joints =
                skin.joints
                    .iter()
                    .map(|j| {
                        graph.record_of.get(&j.value()).copied().ok_or_else(|| {
                            bad(format!("joint node {} is not in the scene", j.value()))
                        })
                    })
                    .collect::<Result<Vec<usize>, _>>()?;
            let inverse_bind = match skin.inverse_bind_matrices {
                None => vec![Mat4::IDENTITY; joints.len()],
                Some(ai) => {
                    let m = self
                        .read_floats::<16>(ai.value(), "inverse bind matrices")
                        .map_err(|e| bad(e.to_string()))?;
                    if m.len() != joints.len() || m.iter().flatten().any(|x| !x.is_finite()) {
                        return Err(bad(format!(
                            "{} inverse bind matrices (finite) for {} joints",
                            m.len(),
                            joints.len()
                        )));
                    }
                    m.iter().map(Mat4::from_cols_array).collect()
                }
            };
            let (vertex_joints, vertex_weights) = p.vertices;
            if let Some(v) = vertex_joints
                .iter()
                .zip(&vertex_weights)
                .position(|(j, w)| {
                    j.iter()
                        .zip(w)
                        .any(|(&j, &w)| w != 0.0 && j as usize >= joints.len())
                })
            {
                return Err(bad(format!(
                    "vertex {v} names joint {:?}, the skin has {}",
                    vertex_joints[v],
                    joints.len()
                )));
            }
            let mesh = &meshes[p.mesh];
            out.push(Skin {
                instance: p.instance,
                joints,
                inverse_bind,
                vertex_joints,
                vertex_weights,
                bind_positions: mesh.positions.clone(),
                bind_normals: mesh.normals.clone(),
            });
        }
        Ok(out)
    }

    /// The morphed instances met in the walk, with their static weights: the node's
    /// `weights`, else the mesh's, else zeros (a list of the wrong length is padded with
    /// zeros or cut, with a warning).
    fn load_morphs(&mut self, pending: Vec<PendingMorph>, meshes: &[Mesh]) -> Vec<Morph> {
        let root = self.root;
        let mut out = Vec::new();
        for p in pending {
            let (position_deltas, normal_deltas, targets) = p.vertices;
            let node = root.nodes.get(p.node).and_then(|n| n.weights.as_ref());
            let mesh = root
                .meshes
                .get(p.gltf_mesh)
                .and_then(|m| m.weights.as_ref());
            let mut weights = node.or(mesh).cloned().unwrap_or_default();
            if !weights.is_empty() && weights.len() != targets {
                self.warnings.push(format!(
                    "node {} (mesh {}): {} morph target weights for {targets} targets; the missing ones are 0, extra ones ignored",
                    p.node,
                    p.gltf_mesh,
                    weights.len()
                ));
            }
            weights.resize(targets, 0.0);
            for w in &mut weights {
                if !w.is_finite() {
                    *w = 0.0;
                }
            }
            let mesh = &meshes[p.mesh];
            out.push(Morph {
                instance: p.instance,
                node: p.rec,
                weights,
                base_positions: mesh.positions.clone(),
                base_normals: mesh.normals.clone(),
                position_deltas,
                normal_deltas,
            });
        }
        out
    }

    /// Reads the file's animations: the channels that drive the translation, rotation,
    /// scale or morph target weights of a node in `graph`. Channels on other nodes are
    /// dropped silently; unknown paths, transforms of nodes with a `matrix`, and weights
    /// of nodes without morph targets with a warning. `None` when no channel, skin or
    /// morph target is left.
    fn load_animations(
        &mut self,
        graph: Graph,
        skins: Vec<Skin>,
        morphs: Vec<Morph>,
    ) -> Result<Option<Animation>, ErrorKind> {
        use json::animation::{Interpolation as I, Property as P};
        let root = self.root;
        let mut channels = Vec::new();
        let (mut weights, mut unknown, mut on_matrix) = (0usize, 0usize, 0usize);
        for (ai, anim) in root.animations.iter().enumerate() {
            let label = match anim.name.as_deref() {
                Some(n) if !n.is_empty() => format!("animation {ai} ({n:?})"),
                _ => format!("animation {ai}"),
            };
            for (ci, ch) in anim.channels.iter().enumerate() {
                let si = ch.sampler.value();
                let ni = ch.target.node.value();
                let sampler = anim.samplers.get(si).ok_or_else(|| {
                    invalid(format!(
                        "{label} channel {ci}: sampler {si} does not exist (the animation has {} sampler(s))",
                        anim.samplers.len()
                    ))
                })?;
                if ni >= root.nodes.len() {
                    return Err(invalid(format!(
                        "{label} channel {ci}: target node {ni} does not exist"
                    )));
                }
                // `None`: morph target weights.
                let property = match ch.target.path {
                    Checked::Valid(P::Translation) => Some(animation::Property::Translation),
                    Checked::Valid(P::Rotation) => Some(animation::Property::Rotation),
                    Checked::Valid(P::Scale) => Some(animation::Property::Scale),
                    Checked::Valid(P::MorphTargetWeights) => None,
                    Checked::Invalid => {
                        unknown += 1;
                        continue;
                    }
                };
                // Channels on nodes outside the loaded scene graph change nothing.
                let Some(&rec) = graph.record_of.get(&ni) else {
                    continue;
                };
                if property.is_some() && matches!(graph.nodes[rec].local, NodeTransform::Matrix(_))
                {
                    on_matrix += 1;
                    continue;
                }
                let targets = match (property, morphs.iter().find(|m| m.node == rec)) {
                    (Some(_), _) => 0,
                    (None, Some(m)) => m.target_count(),
                    (None, None) => {
                        weights += 1;
                        continue;
                    }
                };
                let interpolation = match sampler.interpolation {
                    Checked::Valid(I::Linear) => animation::Interpolation::Linear,
                    Checked::Valid(I::Step) => animation::Interpolation::Step,
                    Checked::Valid(I::CubicSpline) => animation::Interpolation::CubicSpline,
                    Checked::Invalid => {
                        return Err(invalid(format!(
                            "{label} channel {ci} (sampler {si}): unknown interpolation (expected LINEAR, STEP or CUBICSPLINE)"
                        )));
                    }
                };
                let ctx = format!(
                    "{label} channel {ci} (sampler {si}: {} {} of node {ni})",
                    interpolation.name(),
                    property.map_or("weights", animation::Property::name)
                );
                let input = sampler.input.value();
                let output = sampler.output.value();
                let times: Vec<f32> = self
                    .read_floats::<1>(input, "an animation input (key times)")
                    .map_err(|e| in_animation(&ctx, "input", e))?
                    .into_iter()
                    .map(|[t]| t)
                    .collect();
                let read = |v: Vec<Vec4>, property| {
                    Channel::new(rec, property, interpolation, times.clone(), v).map_err(|e| {
                        invalid(format!(
                            "{ctx}: input accessor {input}, output accessor {output}: {e}"
                        ))
                    })
                };
                let output = |this: &mut Self, what: &str| -> Result<Vec<Vec4>, ErrorKind> {
                    Ok(match what {
                        "rotation" => (this.read_floats::<4>(output, "a rotation output"))
                            .map_err(|e| in_animation(&ctx, "output", e))?
                            .into_iter()
                            .map(Vec4::from)
                            .collect(),
                        _ => (this.read_floats::<3>(output, "a translation or scale output"))
                            .map_err(|e| in_animation(&ctx, "output", e))?
                            .into_iter()
                            .map(|v| Vec3::from(v).extend(0.0))
                            .collect(),
                    })
                };
                match property {
                    Some(p) => channels.push(read(output(self, p.name())?, p)?),
                    None => {
                        let flat = (self
                            .read_floats::<1>(sampler.output.value(), "a weights output"))
                        .map_err(|e| in_animation(&ctx, "output", e))?;
                        for (c, values) in weight_chunks(&flat, targets)
                            .map_err(|e| {
                                invalid(format!(
                                    "{ctx}: output accessor {}: {e}",
                                    sampler.output.value()
                                ))
                            })?
                            .into_iter()
                            .enumerate()
                        {
                            channels.push(read(values, animation::Property::Weights(c as u16))?);
                        }
                    }
                }
            }
        }
        if weights > 0 {
            self.warnings.push(format!(
                "{weights} animation channel(s) on the weights of nodes without morph targets ignored"
            ));
        }
        if unknown > 0 {
            self.warnings.push(format!(
                "{unknown} animation channel(s) with an unknown target path ignored"
            ));
        }
        if on_matrix > 0 {
            self.warnings.push(format!(
                "{on_matrix} animation channel(s) ignored: they target nodes with a matrix, which glTF 2.0 does not allow to animate"
            ));
        }
        if channels.is_empty() && skins.is_empty() && morphs.is_empty() {
            return Ok(None);
        }
        Ok(Some(Animation {
            nodes: graph.nodes,
            instance_nodes: graph.instance_nodes,
            channels,
            globals: Vec::new(),
            skins,
            morphs,
        }))
    }

    /// One warning listing image files that are missing (the materials' texture warning
    /// says which of them were needed).
    fn warn_missing_images(&mut self, base_dir: Option<&Path>) {
        let Some(dir) = base_dir else { return };
        let files: Vec<&str> = self
            .root
            .images
            .iter()
            .filter_map(|i| i.uri.as_deref())
            .filter(|u| !u.starts_with("data:") && !is_remote(u))
            .collect();
        let missing: Vec<&str> = files
            .iter()
            .copied()
            .filter(|u| !dir.join(percent_decode(u)).is_file())
            .collect();
        if !missing.is_empty() {
            let shown: Vec<&str> = missing.iter().copied().take(4).collect();
            self.warnings.push(format!(
                "{} of {} image file(s) are missing ({}{})",
                missing.len(),
                files.len(),
                shown.join(", "),
                if missing.len() > shown.len() {
                    ", ..."
                } else {
                    ""
                }
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%20b.bin"), "a b.bin");
        assert_eq!(percent_decode("bad%2"), "bad%2");
        assert_eq!(percent_decode("%zz"), "%zz");
        assert_eq!(percent_decode("x%"), "x%");
    }

    #[test]
    fn data_uris() {
        assert_eq!(
            decode_data_uri("data:application/octet-stream;base64,AQID").expect("ok"),
            vec![1, 2, 3]
        );
        assert!(decode_data_uri("data:text/plain,abc").is_err());
        assert!(decode_data_uri("data:;base64,@@@").is_err());
    }
}
