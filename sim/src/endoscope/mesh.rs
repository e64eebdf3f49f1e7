//! The instrument as triangle meshes: a parametric laparoscopic instrument (shaft, wrist
//! link, two jaws), OBJ files written and read with `tobj`.
//!
//! **Frame `{i}`** (the instrument frame, metres): origin on the shaft axis at the shaft's
//! distal end, `z` along the axis toward the tip (the shaft occupies `z ∈ [−length, 0]`), `x`
//! and `y` complete a right-handed frame; it is the calibration's PSM tip frame `F3` rolled
//! about `z` (`docs/calibration.md`). Each part is meshed in its own *joint frame* in the
//! reference pose (all joints zero) and posed by [`InstrumentGeometry::part_poses`]:
//!
//! - shaft: joint frame = `{i}`;
//! - wrist link: `Rx(wrist)` at the origin of `{i}` (pitch about `x`), length `wrist_length_m`
//!   along its `z`;
//! - jaws: hinged at the wrist link's distal end (the *jaw pivot*, the ground truth's tip
//!   point) about the wrist's `y` axis; jaw 1 on the `+x` side opens by `Ry(+jaw1)`, jaw 2 on
//!   the `−x` side by `Ry(−jaw2)`. Angles ≥ 0 open the jaws.
//!
//! OBJ convention: one object (`o NAME`) per part, named `shaft`, `wrist`, `jaw_1`, `jaw_2`,
//! vertices in metres in the part's joint frame, counter-clockwise faces seen from outside
//! (back faces are culled). An object with another name is rigid with the shaft. Normals are
//! read when present, computed (area-weighted) otherwise.

use std::io::{BufRead, Write};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A part of the instrument: which joint moves it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Part {
    /// The shaft (rigid with `{i}`).
    Shaft,
    /// The wrist link (pitch `wrist` about `x`).
    Wrist,
    /// Jaw 1 (`+x` side).
    Jaw1,
    /// Jaw 2 (`−x` side).
    Jaw2,
}

impl Part {
    /// The OBJ object name of the part.
    pub fn obj_name(self) -> &'static str {
        match self {
            Part::Shaft => "shaft",
            Part::Wrist => "wrist",
            Part::Jaw1 => "jaw_1",
            Part::Jaw2 => "jaw_2",
        }
    }

    fn from_obj_name(name: &str) -> Part {
        match name {
            "wrist" => Part::Wrist,
            "jaw_1" => Part::Jaw1,
            "jaw_2" => Part::Jaw2,
            _ => Part::Shaft,
        }
    }
}

/// A triangle mesh in one part's joint frame (metres); `normals[i]` is the unit normal at
/// `positions[i]`, triangles index both.
#[derive(Clone, Debug, PartialEq)]
pub struct TriMesh {
    /// Vertex positions, metres.
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals (same frame).
    pub normals: Vec<[f32; 3]>,
    /// Triangles (counter-clockwise seen from outside).
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    fn new() -> Self {
        Self { positions: Vec::new(), normals: Vec::new(), triangles: Vec::new() }
    }

    fn vertex(&mut self, p: Vector3<f64>, n: Vector3<f64>) -> u32 {
        let n = n.try_normalize(1e-12).unwrap_or_else(Vector3::z);
        self.positions.push([p.x as f32, p.y as f32, p.z as f32]);
        self.normals.push([n.x as f32, n.y as f32, n.z as f32]);
        (self.positions.len() - 1) as u32
    }

    /// The mesh as a list of triangles of positions (for comparisons independent of the
    /// vertex order).
    pub fn triangle_soup(&self) -> Vec<[[f32; 3]; 3]> {
        self.triangles
            .iter()
            .map(|t| [self.positions[t[0] as usize], self.positions[t[1] as usize], self.positions[t[2] as usize]])
            .collect()
    }

    /// Appends a capped cylinder (or truncated cone) along `z` from `z0` to `z1` with radii
    /// `r0`, `r1`, `segments` sides, flat caps, in this mesh's frame.
    fn cylinder(&mut self, z0: f64, z1: f64, r0: f64, r1: f64, segments: usize) {
        let seg = segments.max(3);
        let slope = (r0 - r1) / (z1 - z0); // outward normal's z component per unit radius
        let ring = |m: &mut TriMesh, z: f64, r: f64| -> u32 {
            let first = m.positions.len() as u32;
            for k in 0..seg {
                let a = std::f64::consts::TAU * k as f64 / seg as f64;
                let (s, c) = a.sin_cos();
                m.vertex(Vector3::new(r * c, r * s, z), Vector3::new(c, s, slope));
            }
            first
        };
        let a0 = ring(self, z0, r0);
        let a1 = ring(self, z1, r1);
        let seg32 = seg as u32;
        for k in 0..seg32 {
            let k1 = (k + 1) % seg32;
            self.triangles.push([a0 + k, a0 + k1, a1 + k1]);
            self.triangles.push([a0 + k, a1 + k1, a1 + k]);
        }
        // Caps: their own vertices (flat normals).
        for (z, r, sign) in [(z0, r0, -1.0), (z1, r1, 1.0)] {
            if r <= 0.0 {
                continue;
            }
            let n = Vector3::new(0.0, 0.0, sign);
            let centre = self.vertex(Vector3::new(0.0, 0.0, z), n);
            let first = self.positions.len() as u32;
            for k in 0..seg {
                let a = std::f64::consts::TAU * k as f64 / seg as f64;
                self.vertex(Vector3::new(r * a.cos(), r * a.sin(), z), n);
            }
            for k in 0..seg32 {
                let k1 = (k + 1) % seg32;
                if sign > 0.0 {
                    self.triangles.push([centre, first + k, first + k1]);
                } else {
                    self.triangles.push([centre, first + k1, first + k]);
                }
            }
        }
    }

    /// Appends a convex hexahedron given its 8 corners (bottom face `0..4` at the proximal
    /// end, top face `4..8` at the distal end, both counter-clockwise seen from `+z`), with
    /// flat face normals.
    fn hexahedron(&mut self, c: [Vector3<f64>; 8]) {
        let faces: [[usize; 4]; 6] =
            [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]];
        for f in faces {
            let n = (c[f[1]] - c[f[0]]).cross(&(c[f[2]] - c[f[0]]));
            let i: Vec<u32> = f.iter().map(|&k| self.vertex(c[k], n)).collect();
            self.triangles.push([i[0], i[1], i[2]]);
            self.triangles.push([i[0], i[2], i[3]]);
        }
    }
}

/// Dimensions of the parametric instrument (metres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InstrumentGeometry {
    /// Shaft diameter, metres (8 mm: a common laparoscopic size; 5 mm and 10 mm exist).
    pub shaft_diameter_m: f64,
    /// Shaft length, metres (from the distal end back; it passes through the trocar).
    pub shaft_length_m: f64,
    /// Wrist link length, metres (from the shaft end to the jaw pivot).
    pub wrist_length_m: f64,
    /// Wrist link diameter, metres (at most the shaft's).
    pub wrist_diameter_m: f64,
    /// Jaw length, metres (from the pivot to the jaw tip).
    pub jaw_length_m: f64,
    /// Sides of the shaft and wrist cylinders.
    pub segments: usize,
}

impl Default for InstrumentGeometry {
    fn default() -> Self {
        Self {
            shaft_diameter_m: 0.008,
            shaft_length_m: 0.35,
            wrist_length_m: 0.010,
            wrist_diameter_m: 0.0075,
            jaw_length_m: 0.018,
            segments: 40,
        }
    }
}

/// Why instrument dimensions are unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    /// A dimension is not finite and positive, or the wrist is wider than the shaft.
    #[error("instrument dimensions must be finite and positive, wrist no wider than the shaft, 3..=512 segments ({0})")]
    Dimension(&'static str),
}

impl InstrumentGeometry {
    /// Shaft radius, metres.
    pub fn shaft_radius_m(&self) -> f64 {
        self.shaft_diameter_m / 2.0
    }

    /// Checks the dimensions.
    pub fn validate(&self) -> Result<(), GeometryError> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        for (v, name) in [
            (self.shaft_diameter_m, "shaft_diameter_m"),
            (self.shaft_length_m, "shaft_length_m"),
            (self.wrist_length_m, "wrist_length_m"),
            (self.wrist_diameter_m, "wrist_diameter_m"),
            (self.jaw_length_m, "jaw_length_m"),
        ] {
            if !pos(v) {
                return Err(GeometryError::Dimension(name));
            }
        }
        if self.wrist_diameter_m > self.shaft_diameter_m {
            return Err(GeometryError::Dimension("wrist_diameter_m"));
        }
        if !(3..=512).contains(&self.segments) {
            return Err(GeometryError::Dimension("segments"));
        }
        Ok(())
    }

    /// The parametric instrument mesh (each part in its joint frame).
    pub fn mesh(&self) -> Result<InstrumentMesh, GeometryError> {
        self.validate()?;
        let r = self.shaft_radius_m();
        let rw = self.wrist_diameter_m / 2.0;
        let mut shaft = TriMesh::new();
        shaft.cylinder(-self.shaft_length_m, 0.0, r, r, self.segments);
        let mut wrist = TriMesh::new();
        // The wrist link: a cylinder ending in a clevis around the jaw pivot.
        wrist.cylinder(0.0, self.wrist_length_m, rw, rw * 0.9, self.segments);
        let jaw = |side: f64| {
            // A tapering half-jaw: from the pivot (width 0.8·rw, half thickness 0.9·rw) to a
            // rounded-off tip; the inner face lies on x = 0 (closed jaws touch there).
            let (w0, w1) = (0.8 * rw, 0.35 * rw);
            let (t0, t1) = (0.9 * rw, 0.35 * rw);
            let l = self.jaw_length_m;
            let x = |t: f64| side * t;
            let mut c = [
                Vector3::new(0.0, -w0, 0.0),
                Vector3::new(x(t0), -w0, 0.0),
                Vector3::new(x(t0), w0, 0.0),
                Vector3::new(0.0, w0, 0.0),
                Vector3::new(0.0, -w1, l),
                Vector3::new(x(t1), -w1, l),
                Vector3::new(x(t1), w1, l),
                Vector3::new(0.0, w1, l),
            ];
            if side < 0.0 {
                // Mirror image: keep the faces counter-clockwise from outside.
                c.swap(1, 3);
                c.swap(5, 7);
            }
            let mut m = TriMesh::new();
            m.hexahedron(c);
            m
        };
        Ok(InstrumentMesh {
            parts: vec![(Part::Shaft, shaft), (Part::Wrist, wrist), (Part::Jaw1, jaw(1.0)), (Part::Jaw2, jaw(-1.0))],
        })
    }

    /// Pose of each part's joint frame in `{i}` for wrist pitch `wrist_rad` and jaw angles
    /// `jaw_rad` (radians): `[shaft, wrist, jaw 1, jaw 2]`.
    pub fn part_poses(&self, wrist_rad: f64, jaw_rad: [f64; 2]) -> [Isometry3<f64>; 4] {
        let wrist = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), wrist_rad),
        );
        let pivot = wrist * Translation3::new(0.0, 0.0, self.wrist_length_m);
        let jaw = |a: f64| pivot * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), a);
        [Isometry3::identity(), wrist, jaw(jaw_rad[0]), jaw(-jaw_rad[1])]
    }

    /// The jaw pivot (the ground truth's tip point) in `{i}`, metres.
    pub fn jaw_pivot(&self, wrist_rad: f64) -> Vector3<f64> {
        self.part_poses(wrist_rad, [0.0; 2])[1] * Vector3::new(0.0, 0.0, self.wrist_length_m)
    }

    /// The two jaw tips (centre of each jaw's distal face) in `{i}`, metres.
    pub fn jaw_tips(&self, wrist_rad: f64, jaw_rad: [f64; 2]) -> [Vector3<f64>; 2] {
        let p = self.part_poses(wrist_rad, jaw_rad);
        let t = 0.175 * self.wrist_diameter_m;
        [
            (p[2] * nalgebra::Point3::new(t, 0.0, self.jaw_length_m)).coords,
            (p[3] * nalgebra::Point3::new(-t, 0.0, self.jaw_length_m)).coords,
        ]
    }
}

/// An instrument: its parts' meshes, each in its joint frame.
#[derive(Clone, Debug, PartialEq)]
pub struct InstrumentMesh {
    /// The parts (a part may appear more than once: an OBJ with several objects).
    pub parts: Vec<(Part, TriMesh)>,
}

/// Why an OBJ could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ObjError {
    /// The OBJ text is malformed (tobj's reason).
    #[error("malformed OBJ: {0}")]
    Parse(#[from] tobj::LoadError),
    /// The file holds no triangle.
    #[error("the OBJ holds no triangle")]
    Empty,
    /// A coordinate is NaN or infinite.
    #[error("object {object:?}: a vertex coordinate or normal is not finite")]
    NotFinite {
        /// The object's name.
        object: String,
    },
    /// Normals given for some vertices only, or a triangle index out of range.
    #[error("object {object:?}: inconsistent indices or normals")]
    Inconsistent {
        /// The object's name.
        object: String,
    },
    /// The file cannot be opened or read.
    #[error("cannot read the OBJ file: {0}")]
    Io(#[from] std::io::Error),
}

impl InstrumentMesh {
    /// Number of triangles over all parts.
    pub fn triangle_count(&self) -> usize {
        self.parts.iter().map(|(_, m)| m.triangles.len()).sum()
    }

    /// Writes the mesh as OBJ text (one object per part, `v`, `vn`, `f v//vn`; floats in
    /// their shortest exact form, so reading gives the same `f32`s back).
    pub fn write_obj(&self, w: &mut impl Write) -> std::io::Result<()> {
        writeln!(w, "# comanip simulated instrument: metres, each part in its joint frame (sim::endoscope::mesh)")?;
        let mut base = 1u32;
        for (part, m) in &self.parts {
            writeln!(w, "o {}", part.obj_name())?;
            for p in &m.positions {
                writeln!(w, "v {} {} {}", p[0], p[1], p[2])?;
            }
            for n in &m.normals {
                writeln!(w, "vn {} {} {}", n[0], n[1], n[2])?;
            }
            for t in &m.triangles {
                let (a, b, c) = (t[0] + base, t[1] + base, t[2] + base);
                writeln!(w, "f {a}//{a} {b}//{b} {c}//{c}")?;
            }
            base += m.positions.len() as u32;
        }
        Ok(())
    }

    /// Reads an OBJ (polygons are triangulated; materials are ignored).
    pub fn read_obj(r: &mut impl BufRead) -> Result<Self, ObjError> {
        let opts = tobj::LoadOptions { single_index: true, triangulate: true, ignore_points: true, ignore_lines: true };
        let (models, _materials) = tobj::load_obj_buf(r, &opts, |_| Ok((Vec::new(), Default::default())))?;
        let mut parts = Vec::new();
        for model in models {
            let m = &model.mesh;
            let object = model.name.clone();
            if m.positions.len() % 3 != 0 || m.indices.len() % 3 != 0 {
                return Err(ObjError::Inconsistent { object });
            }
            let n_vert = m.positions.len() / 3;
            if m.indices.iter().any(|&i| i as usize >= n_vert) {
                return Err(ObjError::Inconsistent { object });
            }
            if !m.normals.is_empty() && m.normals.len() != m.positions.len() {
                return Err(ObjError::Inconsistent { object });
            }
            if !m.positions.iter().chain(m.normals.iter()).all(|v| v.is_finite()) {
                return Err(ObjError::NotFinite { object });
            }
            if m.indices.is_empty() {
                continue;
            }
            let positions: Vec<[f32; 3]> = m.positions.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let triangles: Vec<[u32; 3]> = m.indices.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let normals = if m.normals.is_empty() {
                computed_normals(&positions, &triangles)
            } else {
                m.normals
                    .chunks_exact(3)
                    .map(|c| {
                        // Keep unit normals bit for bit; normalise the others.
                        let l2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
                        if (l2 - 1.0).abs() < 1e-5 { [c[0], c[1], c[2]] } else { normalised([c[0], c[1], c[2]]) }
                    })
                    .collect()
            };
            parts.push((Part::from_obj_name(&model.name), TriMesh { positions, normals, triangles }));
        }
        if parts.is_empty() {
            return Err(ObjError::Empty);
        }
        Ok(Self { parts })
    }

    /// Reads an OBJ file (see [`InstrumentMesh::read_obj`]).
    pub fn load_obj(path: &std::path::Path) -> Result<Self, ObjError> {
        let file = std::fs::File::open(path)?;
        Self::read_obj(&mut std::io::BufReader::new(file))
    }
}

fn normalised(n: [f32; 3]) -> [f32; 3] {
    let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if l > 0.0 { [n[0] / l, n[1] / l, n[2] / l] } else { [0.0, 0.0, 1.0] }
}

fn computed_normals(p: &[[f32; 3]], t: &[[u32; 3]]) -> Vec<[f32; 3]> {
    let mut n = vec![[0.0f32; 3]; p.len()];
    for tri in t {
        let [a, b, c] = tri.map(|i| Vector3::from(p[i as usize]));
        let f = (b - a).cross(&(c - a)); // area-weighted
        for &i in tri {
            for k in 0..3 {
                n[i as usize][k] += f[k];
            }
        }
    }
    n.into_iter().map(normalised).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_round_trip_preserves_the_mesh() {
        let mesh = InstrumentGeometry::default().mesh().unwrap();
        let mut text = Vec::new();
        mesh.write_obj(&mut text).unwrap();
        let back = InstrumentMesh::read_obj(&mut &text[..]).unwrap();
        assert_eq!(back.parts.len(), mesh.parts.len());
        for ((pa, a), (pb, b)) in mesh.parts.iter().zip(&back.parts) {
            assert_eq!(pa, pb);
            assert_eq!(a.triangles.len(), b.triangles.len());
            assert_eq!(a.triangle_soup(), b.triangle_soup(), "part {pa:?}");
            // Normals per triangle corner, exact.
            for (ta, tb) in a.triangles.iter().zip(&b.triangles) {
                for k in 0..3 {
                    assert_eq!(a.normals[ta[k] as usize], b.normals[tb[k] as usize]);
                }
            }
        }
    }

    #[test]
    fn malformed_obj_gives_typed_errors() {
        let bad = b"o shaft\nv 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n";
        assert!(matches!(InstrumentMesh::read_obj(&mut &bad[..]), Err(ObjError::Parse(_))));
        let out_of_range = b"o shaft\nv 0 0 0\nv 1 0 0\nf 1 2 7\n";
        assert!(matches!(InstrumentMesh::read_obj(&mut &out_of_range[..]), Err(ObjError::Parse(_))));
        let empty = b"# nothing\nv 0 0 0\n";
        assert!(matches!(InstrumentMesh::read_obj(&mut &empty[..]), Err(ObjError::Empty)));
        let nan = b"o jaw_1\nv 0 0 0\nv 1 0 0\nv 0 NaN 0\nf 1 2 3\n";
        assert!(matches!(InstrumentMesh::read_obj(&mut &nan[..]), Err(ObjError::NotFinite { .. })));
    }

    #[test]
    fn user_obj_without_normals_loads_rigid_with_the_shaft() {
        let obj = b"o my_tool\nv 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nv 0 0 0.01\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n";
        let m = InstrumentMesh::read_obj(&mut &obj[..]).unwrap();
        assert_eq!(m.parts.len(), 1);
        assert_eq!(m.parts[0].0, Part::Shaft);
        assert_eq!(m.triangle_count(), 4);
        for n in &m.parts[0].1.normals {
            assert!(((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn generated_mesh_is_closed_and_outward() {
        // Each part: the signed volume (divergence theorem) is positive: faces point outward.
        let mesh = InstrumentGeometry::default().mesh().unwrap();
        // Signed volume of a closed triangle soup (divergence theorem), cubic metres.
        let volume = |m: &TriMesh| -> f64 {
            m.triangle_soup()
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64));
                    a.dot(&b.cross(&c)) / 6.0
                })
                .sum()
        };
        for (part, m) in &mesh.parts {
            let vol = volume(m);
            assert!(vol > 0.0, "{part:?} has signed volume {vol}");
        }
        let g = InstrumentGeometry::default();
        let r = g.shaft_radius_m();
        let expected = std::f64::consts::PI * r * r * g.shaft_length_m;
        let shaft_vol = volume(&mesh.parts[0].1);
        assert!((shaft_vol / expected - 1.0).abs() < 0.01, "{shaft_vol} vs {expected}");
    }
}
