//! Why a scene could not be loaded.

/// A scene that could not be loaded or written: the file (or `builtin:` spec) and the cause.
///
/// Displays as `"<path>: <cause>"`, for example
/// `"scenes/a.glb: accessor 3 reads past the end of buffer 0 (needs 1200 bytes, has 800)"`.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {kind}")]
pub struct SceneError {
    /// The file, or the scene spec, at fault.
    pub path: String,
    /// What is wrong with it.
    pub kind: ErrorKind,
}

impl SceneError {
    /// An error for this file or spec.
    pub fn new(path: impl Into<String>, kind: ErrorKind) -> Self {
        SceneError {
            path: path.into(),
            kind,
        }
    }
}

/// The cause of a [`SceneError`].
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The file (or a buffer file it names) could not be read or written.
    #[error("{what}: {source}")]
    Io {
        /// What was being read or written.
        what: String,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// A `.glb` file that does not start with the GLB magic `glTF`.
    #[error("not a binary glTF file: wrong magic {found:?} (expected \"glTF\")")]
    BadMagic {
        /// The first four bytes, as text with escapes.
        found: String,
    },
    /// The file ends before its own headers say it does.
    #[error("the file is truncated: {0}")]
    Truncated(String),
    /// A `.hair` file (Cem Yuksel's format) that is malformed: its magic, its counts, or
    /// its strands.
    #[error("malformed .hair file: {0}")]
    Hair(String),
    /// The GLB container is malformed (version, chunk types, lengths).
    #[error("malformed GLB container: {0}")]
    Glb(String),
    /// The glTF JSON does not parse, or does not have the glTF shape.
    #[error("JSON error: {0}")]
    Json(String),
    /// The glTF parses but breaks the specification (invalid indices, missing fields...).
    #[error("invalid glTF: {0}")]
    Invalid(String),
    /// The file lists an extension in `extensionsRequired` that this loader cannot honour
    /// (compressed geometry such as `KHR_draco_mesh_compression`, `EXT_meshopt_compression`).
    #[error(
        "requires the unsupported glTF extension {0} (listed in extensionsRequired); decompress the geometry first (e.g. with a glTF tool such as gltf-transform)"
    )]
    UnsupportedExtension(String),
    /// An accessor (or the buffer view under it) reads past the end of its data.
    #[error("accessor {accessor} reads past the end of {target} (needs {needs} bytes, has {has})")]
    AccessorOutOfBounds {
        /// The accessor's index.
        accessor: usize,
        /// What it overruns, as text: `"buffer 0"` or `"buffer view 2"`.
        target: String,
        /// The byte length the read needs.
        needs: u64,
        /// The byte length there is.
        has: u64,
    },
    /// An accessor that cannot be read for another reason (type, stride, sparse indices...).
    #[error("accessor {accessor}: {reason}")]
    Accessor {
        /// The accessor's index.
        accessor: usize,
        /// What is wrong.
        reason: String,
    },
    /// A buffer that cannot be resolved (missing `.bin` file, bad `data:` URI...).
    #[error("buffer {buffer}: {reason}")]
    Buffer {
        /// The buffer's index.
        buffer: usize,
        /// What is wrong.
        reason: String,
    },
    /// A triangle names a vertex past the end of its primitive's vertices.
    #[error(
        "mesh {mesh} primitive {primitive}: triangle {triangle} uses vertex index {index}, but the primitive has {vertices} vertices"
    )]
    IndexOutOfRange {
        /// glTF mesh index.
        mesh: usize,
        /// Primitive index in the mesh.
        primitive: usize,
        /// Triangle index in the primitive.
        triangle: usize,
        /// The bad vertex index.
        index: u32,
        /// How many vertices the primitive has.
        vertices: usize,
    },
    /// A vertex position is NaN or infinite.
    #[error("mesh {mesh} primitive {primitive}: position {vertex} is not finite ({value:?})")]
    NonFinitePosition {
        /// glTF mesh index.
        mesh: usize,
        /// Primitive index in the mesh.
        primitive: usize,
        /// Vertex index in the primitive.
        vertex: usize,
        /// The position.
        value: [f32; 3],
    },
    /// A node's transform, or a world transform, is not finite.
    #[error("node {node}: {reason}")]
    Node {
        /// The node's index.
        node: usize,
        /// What is wrong.
        reason: String,
    },
    /// The scene has no triangle at all.
    #[error("the scene has no triangles{0}")]
    NoTriangles(String),
    /// The scene is too large for the BVH (or for 32-bit indices).
    #[error("the scene is too large: {0}")]
    TooLarge(String),
    /// The scene geometry, placed in the world, is not finite.
    #[error("{0}")]
    NonFiniteWorld(String),
    /// A spec that names no scene (unknown builtin, bad parameter, bad `#` suffix...).
    #[error("bad scene spec: {0}")]
    Spec(String),
}
