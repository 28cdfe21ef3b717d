//! A Wavefront OBJ reader for the bundle's object meshes: `v` and `f` lines only (the
//! catalogue meshes are plain triangle soups; texture coordinates, normals, groups and
//! materials are ignored), polygons fan-triangulated. Every malformed line is an error
//! naming the line, never a panic or a silently wrong mesh.

/// A triangle mesh in the object's own frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    /// Vertex indices, counter-clockwise seen from outside (OBJ's convention).
    pub triangles: Vec<[u32; 3]>,
}

/// Parses OBJ text. Accepts `f` references as `i`, `i/t`, `i//n`, `i/t/n`, with negative
/// (relative) indices; extra `v` components (w, or vertex colours) are ignored.
pub fn parse(text: &str) -> Result<Mesh, String> {
    let mut positions: Vec<[f32; 3]> = Vec::new();
    let mut triangles = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let n = n + 1;
        let line = line.split('#').next().unwrap_or("");
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let mut p = [0.0f32; 3];
                for c in &mut p {
                    let w = words.next().ok_or(format!("line {n}: a vertex needs 3 coordinates"))?;
                    *c = w.parse().map_err(|_| format!("line {n}: {w:?} is not a number"))?;
                    if !c.is_finite() {
                        return Err(format!("line {n}: non-finite coordinate {w:?}"));
                    }
                }
                positions.push(p);
            }
            Some("f") => {
                let corners = words
                    .map(|w| vertex_index(w, positions.len()).map_err(|e| format!("line {n}: {e}")))
                    .collect::<Result<Vec<u32>, String>>()?;
                if corners.len() < 3 {
                    return Err(format!("line {n}: a face needs at least 3 vertices, got {}", corners.len()));
                }
                // A fan is exact for the convex polygons mesh exporters write.
                for k in 1..corners.len() - 1 {
                    triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {} // comments, blank lines, vt/vn/o/g/s/usemtl/mtllib: not needed
        }
    }
    if triangles.is_empty() {
        return Err("no faces (f lines) found".into());
    }
    Ok(Mesh { positions, triangles })
}

/// The 0-based vertex index of one face corner (`7`, `7/2`, `7//3`, `-1`), checked against
/// the `count` vertices defined so far (OBJ references only earlier vertices).
fn vertex_index(word: &str, count: usize) -> Result<u32, String> {
    let first = word.split('/').next().unwrap_or("");
    let i: i64 = first.parse().map_err(|_| format!("{word:?} is not a vertex reference"))?;
    let resolved = match i {
        0 => return Err("vertex index 0 (OBJ indices start at 1)".into()),
        i if i > 0 => i - 1,
        i => count as i64 + i, // -1 = the last vertex defined so far
    };
    if resolved < 0 || resolved >= count as i64 {
        return Err(format!("vertex {i} does not exist ({count} defined so far)"));
    }
    u32::try_from(resolved).map_err(|_| format!("vertex index {i} too large"))
}

impl Mesh {
    /// One vertex per triangle corner with "auto-smooth" normals: a corner averages the
    /// (area-weighted) normals of the faces around its vertex that are within `crease_deg`
    /// of its own face, so a mug's wall is smooth while its rim and bottom stay sharp.
    /// Zero-area triangles are dropped (they have no normal, and a renderer ignores them).
    /// Returns (positions, unit normals), three entries per kept triangle.
    pub fn corners_with_normals(&self, crease_deg: f64) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let p = |i: u32| self.positions[i as usize].map(f64::from);
        // Face normals scaled by twice the area, and the faces around each vertex.
        let mut faces: Vec<([u32; 3], [f64; 3])> = Vec::with_capacity(self.triangles.len());
        for t in &self.triangles {
            let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
            let n = cross(sub(b, a), sub(c, a));
            // Relative threshold: the mesh's own scale decides what "zero area" means.
            let scale = norm(sub(b, a)).max(norm(sub(c, a))).max(1e-30);
            if norm(n) > 1e-10 * scale * scale {
                faces.push((*t, n));
            }
        }
        let mut around: Vec<Vec<usize>> = vec![Vec::new(); self.positions.len()];
        for (f, (t, _)) in faces.iter().enumerate() {
            for &v in t {
                around[v as usize].push(f);
            }
        }
        let cos_crease = crease_deg.to_radians().cos();
        let (mut pos, mut nrm) = (Vec::with_capacity(3 * faces.len()), Vec::with_capacity(3 * faces.len()));
        for (t, n) in &faces {
            let own = normalize(*n);
            for &v in t {
                let mut sum = [0.0f64; 3];
                for &g in &around[v as usize] {
                    let m = faces[g].1;
                    if dot(normalize(m), own) >= cos_crease {
                        sum = [sum[0] + m[0], sum[1] + m[1], sum[2] + m[2]];
                    }
                }
                // `own` is always in the sum, but opposite neighbours could cancel it.
                let s = if norm(sum) > 1e-12 * norm(*n) { normalize(sum) } else { own };
                pos.push(self.positions[v as usize]);
                nrm.push(s.map(|x| x as f32));
            }
        }
        (pos, nrm)
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    [a[0] / n, a[1] / n, a[2] / n]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_vertices_and_polygons() {
        let m = parse(
            "# a unit quad and a triangle\nv 0 0 0\nv 1 0 0 1.0\nv 1 1 0 0.5 0.5 0.5\nv 0 1 0\n\
             vn 0 0 1\nf 1/1/1 2/2/1 3//1 4\ng rest\nf -4 -3 -1 # relative\n",
        )
        .unwrap();
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 3]]);
    }

    #[test]
    fn malformed_obj_is_an_error_with_the_line() {
        for (text, needle) in [
            ("v 0 0\nf 1 1 1", "line 1: a vertex needs 3"),
            ("v 0 0 x\n", "line 1: \"x\" is not a number"),
            ("v 0 0 nan\n", "non-finite"),
            ("v 0 0 0\nf 1 2 3\n", "line 2: vertex 2 does not exist"),
            ("v 0 0 0\nf 0 1 1\n", "vertex index 0"),
            ("v 0 0 0\nf 1 -2 1\n", "vertex -2 does not exist"),
            ("v 0 0 0\nf 1 1\n", "at least 3 vertices"),
            ("v 0 0 0\nf a b c\n", "not a vertex reference"),
            ("v 0 0 0\n", "no faces"),
            ("", "no faces"),
        ] {
            let e = parse(text).unwrap_err();
            assert!(e.contains(needle), "{text:?}: {e}");
        }
    }

    #[test]
    fn normals_are_unit_smooth_within_the_crease_and_drop_degenerate_faces() {
        // Two faces of a cube sharing an edge (90°) plus a flat neighbour (0°) and a
        // zero-area sliver.
        let m = Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
                [2.0, 0.0, 0.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3], [0, 4, 1], [0, 1, 5]],
        };
        let (p, n) = m.corners_with_normals(40.0);
        assert_eq!((p.len(), n.len()), (9, 9), "the sliver [0,1,5] is dropped");
        for v in &n {
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((l - 1.0).abs() < 1e-6);
        }
        // The two z-facing triangles stay +z (the 90° side face is beyond the crease).
        for v in &n[..6] {
            assert!((v[2] - 1.0).abs() < 1e-6, "{v:?}");
        }
        for v in &n[6..] {
            assert!((v[1] - 1.0).abs() < 1e-6, "{v:?}");
        }
    }
}
