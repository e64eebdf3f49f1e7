//! The tracked instrument: the tool arm's forward kinematics to the instrument, the
//! instrument's parts (shaft, wrist link, two jaws) as welded triangle meshes with their edge
//! adjacency (the paper's silhouette-edge test, Eq. 6 and Algorithm 1), and the stereo cameras
//! of one frame.
//!
//! Frames (metres, radians):
//! - `{b}` the tool arm's base frame (`docs/kinematics.md`); `{6}` its last DH frame (origin at
//!   the wrist centre P, `z` along the instrument);
//! - `{i}` the instrument frame: `{6}` moved by `instrument_length_m − wrist_length_m` along `z`
//!   (origin at the shaft's distal end, `z` toward the tip), as the simulator renders it;
//! - the tool tip is the jaw pivot, `{6}` moved by `instrument_length_m` along `z`;
//! - each eye's camera frame `{c}`: `z` forward, `x` right, `y` down; pixels are measured
//!   (distorted) pixels of [`Intrinsics::project`], centre of the top-left pixel at `(0, 0)`.

use estimator::calib::Intrinsics;
use estimator::kinematics::{Achilles, JOINTS};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// Which joint moves a part of the instrument.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Part {
    /// The shaft, rigid with `{i}`.
    Shaft,
    /// The wrist link (rigid with `{i}`: the Achilles arm's instrument has no wrist pitch joint
    /// of its own; its passive wrist is the arm's joints 4-6).
    Wrist,
    /// Jaw 1 (`+x` side), hinged at the jaw pivot about `y`, opens by `Ry(+jaw)`.
    Jaw1,
    /// Jaw 2 (`−x` side), opens by `Ry(−jaw)`.
    Jaw2,
}

/// A part's triangle mesh in its joint frame (metres; triangles counter-clockwise seen from
/// outside, so that `(v1 − v0) × (v2 − v0)` points outwards).
#[derive(Clone, Debug, PartialEq)]
pub struct PartMesh {
    /// Which joint moves it.
    pub part: Part,
    /// Vertex positions, metres, in the part's joint frame.
    pub positions: Vec<[f32; 3]>,
    /// Triangles, indices into `positions`.
    pub triangles: Vec<[u32; 3]>,
}

/// Dimensions the tracker needs (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToolGeometry {
    /// From the wrist centre P to the jaw pivot (the tip), metres (the scenario's instrument
    /// length).
    pub instrument_length_m: f64,
    /// From the shaft's distal end to the jaw pivot, metres.
    pub wrist_length_m: f64,
    /// Shaft radius, metres.
    pub shaft_radius_m: f64,
    /// Length of shaft modelled back from its distal end, metres (the paper keeps 10 cm: the
    /// rest is out of view).
    pub shaft_modelled_m: f64,
}

/// Why a tool model cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    /// A dimension is not finite and positive, or the wrist is longer than the instrument.
    #[error("tool geometry: {0} must be finite and positive (wrist shorter than the instrument)")]
    Geometry(&'static str),
    /// A mesh is empty, indexes a missing vertex or has a non-finite vertex.
    #[error("mesh of part {part:?}: {problem}")]
    Mesh {
        /// The part.
        part: Part,
        /// What is wrong.
        problem: &'static str,
    },
}

/// One edge of a welded mesh between two faces.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct MeshEdge {
    pub a: Vector3<f64>,
    pub b: Vector3<f64>,
    /// A point and the outward normal of each adjacent face (part frame).
    pub p0: Vector3<f64>,
    pub n0: Vector3<f64>,
    pub p1: Vector3<f64>,
    pub n1: Vector3<f64>,
}

impl MeshEdge {
    /// Eq. 6: the edge joins a front-facing and a back-facing face seen from `eye` (the camera
    /// centre in the part's frame).
    #[inline]
    pub fn is_silhouette(&self, eye: &Vector3<f64>) -> bool {
        let s0 = (self.p0 - eye).dot(&self.n0);
        let s1 = (self.p1 - eye).dot(&self.n1);
        s0 * s1 < 0.0
    }
}

/// A part's welded mesh as edges with their two faces.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct PartEdges {
    pub part: Part,
    /// Every edge shared by two faces (the paper's Algorithm 1 visits them all).
    pub all: Vec<MeshEdge>,
    /// The candidates: edges whose faces are not coplanar (a flat face's diagonals can never be
    /// silhouette edges), precomputed once (ours).
    pub candidates: Vec<MeshEdge>,
}

fn weld(m: &PartMesh) -> Result<PartEdges, ModelError> {
    let bad = |problem| ModelError::Mesh { part: m.part, problem };
    if m.triangles.is_empty() {
        return Err(bad("no triangles"));
    }
    if m.positions.iter().flatten().any(|v| !v.is_finite()) {
        return Err(bad("a vertex is not finite"));
    }
    // Weld vertices by position (0.1 µm grid): a cylinder's caps and the hexahedra's faces
    // carry vertices of their own.
    let key = |p: &[f32; 3]| p.map(|v| (f64::from(v) * 1e7).round() as i64);
    let mut ids: Vec<([i64; 3], u32)> = Vec::with_capacity(m.positions.len());
    let mut remap = vec![0u32; m.positions.len()];
    let mut welded: Vec<Vector3<f64>> = Vec::new();
    {
        let mut order: Vec<usize> = (0..m.positions.len()).collect();
        order.sort_by_key(|&i| key(&m.positions[i]));
        for i in order {
            let k = key(&m.positions[i]);
            let id = match ids.last() {
                Some((lk, id)) if *lk == k => *id,
                _ => {
                    let p = m.positions[i];
                    welded.push(Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])));
                    let id = (welded.len() - 1) as u32;
                    ids.push((k, id));
                    id
                }
            };
            remap[i] = id;
        }
    }
    let mut faces: Vec<([u32; 3], Vector3<f64>)> = Vec::with_capacity(m.triangles.len());
    for t in &m.triangles {
        let mut w = [0u32; 3];
        for (k, &v) in t.iter().enumerate() {
            w[k] = *remap.get(v as usize).ok_or(bad("a triangle indexes a missing vertex"))?;
        }
        let [a, b, c] = w.map(|i| welded[i as usize]);
        let n = (b - a).cross(&(c - a));
        if let Some(n) = n.try_normalize(1e-18) {
            faces.push((w, n));
        }
    }
    let mut half: Vec<((u32, u32), usize)> = Vec::with_capacity(faces.len() * 3);
    for (f, (w, _)) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (w[k], w[(k + 1) % 3]);
            half.push(((a.min(b), a.max(b)), f));
        }
    }
    half.sort_unstable();
    let mut all = Vec::new();
    let mut candidates = Vec::new();
    for g in half.chunk_by(|x, y| x.0 == y.0) {
        if g.len() != 2 {
            continue;
        }
        let ((a, b), f0) = g[0];
        let f1 = g[1].1;
        let (w0, n0) = faces[f0];
        let (w1, n1) = faces[f1];
        let e = MeshEdge {
            a: welded[a as usize],
            b: welded[b as usize],
            p0: welded[w0[0] as usize],
            n0,
            p1: welded[w1[0] as usize],
            n1,
        };
        all.push(e);
        if n0.dot(&n1) < 1.0 - 1e-9 {
            candidates.push(e);
        }
    }
    Ok(PartEdges { part: m.part, all, candidates })
}

/// The tracked instrument on the tool arm. Built once; every method is allocation-free.
#[derive(Clone, Debug)]
pub struct ToolModel {
    arm: Achilles,
    geometry: ToolGeometry,
    pub(crate) parts: Vec<PartEdges>,
}

impl ToolModel {
    /// A model of the instrument `meshes` (each part in its joint frame, as
    /// `sim::endoscope::mesh` writes them) on the arm `arm`.
    pub fn new(arm: Achilles, geometry: ToolGeometry, meshes: &[PartMesh]) -> Result<Self, ModelError> {
        let g = &geometry;
        for (v, name) in [
            (g.instrument_length_m, "instrument_length_m"),
            (g.wrist_length_m, "wrist_length_m"),
            (g.shaft_radius_m, "shaft_radius_m"),
            (g.shaft_modelled_m, "shaft_modelled_m"),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(ModelError::Geometry(name));
            }
        }
        if g.wrist_length_m >= g.instrument_length_m {
            return Err(ModelError::Geometry("wrist_length_m"));
        }
        let parts = meshes.iter().map(weld).collect::<Result<Vec<_>, _>>()?;
        Ok(Self { arm, geometry, parts })
    }

    /// The dimensions.
    pub fn geometry(&self) -> &ToolGeometry {
        &self.geometry
    }

    /// `T_b_i`: the instrument frame in the base frame for joints `q` (radians), `None` when a
    /// joint is not finite.
    pub fn instrument_in_base(&self, q: &[f64; JOINTS]) -> Option<Isometry3<f64>> {
        let f = self.arm.forward(q).ok()?.flange_base;
        let off = self.geometry.instrument_length_m - self.geometry.wrist_length_m;
        Some(f * Translation3::new(0.0, 0.0, off))
    }

    /// `T_b_tip`: the tip (jaw pivot) frame in the base frame (rotation of `{6}`), metres.
    pub fn tip_in_base(&self, q: &[f64; JOINTS]) -> Option<Isometry3<f64>> {
        let f = self.arm.forward(q).ok()?.flange_base;
        Some(f * Translation3::new(0.0, 0.0, self.geometry.instrument_length_m))
    }

    /// Pose of a part's joint frame in `{i}` for the jaw angle `jaw_rad` (each jaw, radians).
    pub fn part_in_instrument(&self, part: Part, jaw_rad: f64) -> Isometry3<f64> {
        let pivot = Translation3::new(0.0, 0.0, self.geometry.wrist_length_m);
        match part {
            Part::Shaft | Part::Wrist => Isometry3::identity(),
            Part::Jaw1 => pivot * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), jaw_rad),
            Part::Jaw2 => pivot * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -jaw_rad),
        }
    }

    /// Joints' Jacobian of the tip pose by central differences: columns are `d(position)/dq_j`
    /// (metres per radian) stacked over `d(rotation vector)/dq_j`; `None` off the arm.
    pub fn tip_jacobian(&self, q: &[f64; JOINTS]) -> Option<nalgebra::Matrix6<f64>> {
        let mut j = nalgebra::Matrix6::zeros();
        let h = 1e-6;
        let t0 = self.tip_in_base(q)?;
        for k in 0..JOINTS {
            let (mut a, mut b) = (*q, *q);
            a[k] += h;
            b[k] -= h;
            let (ta, tb) = (self.tip_in_base(&a)?, self.tip_in_base(&b)?);
            let dp = (ta.translation.vector - tb.translation.vector) / (2.0 * h);
            let dr = (ta.rotation * tb.rotation.inverse()).scaled_axis() / (2.0 * h);
            let _ = &t0;
            j.fixed_view_mut::<3, 1>(0, k).copy_from(&dp);
            j.fixed_view_mut::<3, 1>(3, k).copy_from(&dr);
        }
        Some(j)
    }
}

/// The stereo cameras of one frame: each eye's intrinsics, the left eye's pose and the right
/// eye relative to the left.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoCameras {
    /// Intrinsics of the left and right eye (measured pixels).
    pub intrinsics: [Intrinsics; 2],
    /// `T_cl_b` = the paper's `g_CB` for the left eye: the tool arm's base in the left camera
    /// frame, metres.
    pub left_from_base: Isometry3<f64>,
    /// `T_cr_cl`: the left camera frame in the right one, metres.
    pub right_from_left: Isometry3<f64>,
}

impl StereoCameras {
    /// True when every number is finite and the intrinsics are valid.
    pub fn is_valid(&self) -> bool {
        let iso_ok = |t: &Isometry3<f64>| {
            t.translation.vector.iter().all(|v| v.is_finite()) && t.rotation.coords.iter().all(|v| v.is_finite())
        };
        iso_ok(&self.left_from_base)
            && iso_ok(&self.right_from_left)
            && self.intrinsics.iter().all(|k| k.validate().is_ok())
    }

    /// `T_c_b` of each eye with the base-to-camera correction `delta` (the augmented state of
    /// Eq. 17: a rotation vector, radians, and a translation, metres, applied on the left of
    /// `g_CB`).
    pub fn eyes_from_base(&self, delta: &[f64; 6]) -> [Isometry3<f64>; 2] {
        let d = Isometry3::new(Vector3::new(delta[3], delta[4], delta[5]), Vector3::new(delta[0], delta[1], delta[2]));
        let left = d * self.left_from_base;
        [left, self.right_from_left * left]
    }
}

/// Projects `p_c` (camera frame, metres) to measured pixels; `None` behind or too near the
/// camera (`z < 1 mm`).
#[inline]
pub(crate) fn project(k: &Intrinsics, p_c: &Vector3<f64>) -> Option<(f64, f64)> {
    if p_c.z < 1e-3 {
        return None;
    }
    let v = k.project(p_c);
    Some((v.x, v.y))
}

/// The camera centre expressed in a frame whose pose in the camera is `t_c_f`.
#[inline]
pub(crate) fn eye_in(t_c_f: &Isometry3<f64>) -> Vector3<f64> {
    (t_c_f.inverse_transform_point(&Point3::origin())).coords
}
