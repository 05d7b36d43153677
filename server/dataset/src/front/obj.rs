//! Wavefront OBJ meshes (3D-FUTURE's `raw_model.obj`).

use std::path::Path;

use super::error::FrontError;

/// A Wavefront OBJ mesh: vertex positions and triangles (polygons fanned).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ObjMesh {
    /// Vertex positions (`v` lines).
    pub vertices: Vec<[f64; 3]>,
    /// Triangles as 0-based indices into `vertices` (`f` lines; `a`, `a/b`, `a//c` and
    /// `a/b/c` references, negative ones relative to the end, polygons fanned from their first
    /// vertex).
    pub triangles: Vec<[u32; 3]>,
}

/// Parses a Wavefront OBJ text; `path` only names the file in errors. Lines other than `v` and
/// `f` (normals, texture coordinates, groups, materials) are ignored.
pub fn parse_obj(text: &str, path: &Path) -> Result<ObjMesh, FrontError> {
    let mut mesh = ObjMesh::default();
    for (number, line) in text.lines().enumerate() {
        let error = |message: String| FrontError::Obj { path: path.to_owned(), line: number + 1, message };
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let mut xyz = [0.0_f64; 3];
                for value in &mut xyz {
                    let word = words.next().ok_or_else(|| error("a `v` line needs three coordinates".into()))?;
                    *value = word.parse().map_err(|_| error(format!("`{word}` is not a number")))?;
                    if !value.is_finite() {
                        return Err(error(format!("coordinate `{word}` is not finite")));
                    }
                }
                mesh.vertices.push(xyz);
            }
            Some("f") => {
                let mut corners = Vec::new();
                for word in words {
                    let first = word.split('/').next().unwrap_or_default();
                    let index: i64 = first.parse().map_err(|_| {
                        error(format!("`{word}` is not a vertex reference (`a`, `a/b`, `a//c`, `a/b/c`)"))
                    })?;
                    let count = mesh.vertices.len() as i64;
                    let resolved = if index > 0 { index - 1 } else { count + index };
                    if index == 0 || !(0..count).contains(&resolved) {
                        return Err(error(format!("vertex {index} does not exist: {count} vertices so far")));
                    }
                    corners.push(resolved as u32);
                }
                if corners.len() < 3 {
                    return Err(error(format!("a face needs at least 3 vertices, this one has {}", corners.len())));
                }
                for k in 1..corners.len() - 1 {
                    mesh.triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    if mesh.vertices.is_empty() {
        return Err(FrontError::Obj { path: path.to_owned(), line: 0, message: "the file has no vertices".into() });
    }
    Ok(mesh)
}
