//! The builder's input: an indexed triangle mesh, checked before anything uses it.

use glam::Vec3;

/// One triangle as three corner positions.
pub type Triangle = [Vec3; 3];

/// An indexed triangle mesh: what every loader hands to the builders.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleMesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// One entry per triangle: three indices into `positions`.
    pub indices: Vec<[u32; 3]>,
}

/// Why a mesh was refused. Every variant names the primitive (triangle) at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// A corner index points past the end of the position array.
    #[error(
        "triangle {triangle}: vertex index {index} is out of range (the mesh has {vertices} vertices)"
    )]
    IndexOutOfRange {
        /// The triangle at fault.
        triangle: usize,
        /// The out-of-range index.
        index: u32,
        /// The number of positions the mesh has.
        vertices: usize,
    },
    /// A corner has a NaN or infinite coordinate.
    #[error("triangle {triangle}: corner {corner} has a non-finite coordinate {value:?}")]
    NonFinite {
        /// The triangle at fault.
        triangle: usize,
        /// Which corner (0, 1, 2).
        corner: usize,
        /// The corner's coordinates.
        value: [f32; 3],
    },
    /// The builder was given more triangles than a 32-bit index can name.
    #[error("{0} triangles is more than this BVH can index (at most {max})", max = crate::flat::MAX_PRIMITIVES)]
    TooMany(usize),
}

impl TriangleMesh {
    /// A mesh from explicit triangles (three new vertices each).
    pub fn from_triangles(tris: &[Triangle]) -> Self {
        let positions = tris.iter().flatten().copied().collect();
        let indices = (0..tris.len() as u32)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect();
        TriangleMesh { positions, indices }
    }

    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// True when the mesh has no triangle.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// Checks every index and coordinate, then returns the triangles as corner triples.
    /// Triangles keep their order, so triangle `i` here is primitive `i` everywhere after.
    pub fn triangles(&self) -> Result<Vec<Triangle>, MeshError> {
        if self.indices.len() > crate::flat::MAX_PRIMITIVES {
            return Err(MeshError::TooMany(self.indices.len()));
        }
        let n = self.positions.len();
        self.indices
            .iter()
            .enumerate()
            .map(|(t, idx)| {
                let mut tri = [Vec3::ZERO; 3];
                for (c, &i) in idx.iter().enumerate() {
                    let p = *self
                        .positions
                        .get(i as usize)
                        .ok_or(MeshError::IndexOutOfRange {
                            triangle: t,
                            index: i,
                            vertices: n,
                        })?;
                    if !p.is_finite() {
                        return Err(MeshError::NonFinite {
                            triangle: t,
                            corner: c,
                            value: p.to_array(),
                        });
                    }
                    tri[c] = p;
                }
                Ok(tri)
            })
            .collect()
    }
}

/// Checks a triangle soup the same way [`TriangleMesh::triangles`] does.
pub fn validate_triangles(tris: &[Triangle]) -> Result<(), MeshError> {
    if tris.len() > crate::flat::MAX_PRIMITIVES {
        return Err(MeshError::TooMany(tris.len()));
    }
    for (t, tri) in tris.iter().enumerate() {
        for (c, p) in tri.iter().enumerate() {
            if !p.is_finite() {
                return Err(MeshError::NonFinite {
                    triangle: t,
                    corner: c,
                    value: p.to_array(),
                });
            }
        }
    }
    Ok(())
}
