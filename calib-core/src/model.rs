//! D-H model, forward kinematics, the pose error and the analytic Jacobians.
//!
//! # Conventions (the contract every other module relies on)
//!
//! * Standard D-H per eq. (1) of the paper: `T_i = Rot_z(θ_i + offset_i) · Tran_z(d_i) ·
//!   Tran_x(a_i) · Rot_x(α_i)`, and `T = T_1 · … · T_N` maps tool-frame coordinates (frame N)
//!   to base-frame coordinates (frame 0). Lengths in metres, angles in radians.
//! * **Pose error frame: the tool frame of the model.** For a model pose `M = (R_m, p_m)` and a
//!   measured pose `A = (R_a, p_a)`,
//!   `e = [R_mᵀ (p_a − p_m) ; log(R_mᵀ R_a)]` (position first, then a rotation vector). This is
//!   `δT = T⁻¹ dT` of eq. (17) to first order, without the Euler-angle singularity of eq. (2).
//!   `‖e‖` is independent of the frame, so the objective y (eq. 10) is unaffected by the choice.
//! * **Parameter ordering** (the paper's eq. 27): index `kind · N + joint`, with kinds in the
//!   order `Δa, Δd, Δα, Δθ` ([`ParamKind`]). The identification Jacobian column of a parameter
//!   is the tool-frame twist `[v; ω]` produced by a unit change of that parameter, so that
//!   `pose_error(fk(table), fk(table + Δ)) ≈ J Δ`. The joint Jacobian is the `Δθ` block.

use nalgebra::{Isometry3, Matrix3, Matrix4, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector3, Vector6};

/// Number of joints of the exocal suit (and of the paper's arm).
pub const SUIT_JOINTS: usize = 7;
/// Number of D-H parameters identified for the suit (`4 · SUIT_JOINTS`).
pub const SUIT_PARAMS: usize = 4 * SUIT_JOINTS;

/// One row of a D-H table (standard convention, eq. 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DhRow {
    /// Link length `a_i` (m), along `x_i`.
    pub a: f64,
    /// Link twist `α_i` (rad), about `x_i`.
    pub alpha: f64,
    /// Link offset `d_i` (m), along `z_{i−1}`.
    pub d: f64,
    /// Joint-angle offset (rad) added to the reported joint angle.
    pub theta_offset: f64,
}

/// The four kinds of D-H parameter, in the order of the parameter vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParamKind {
    /// `a_i` (m).
    A = 0,
    /// `d_i` (m).
    D = 1,
    /// `α_i` (rad).
    Alpha = 2,
    /// Joint-angle offset `θ_i` (rad).
    Theta = 3,
}

impl ParamKind {
    /// All kinds in parameter-vector order.
    pub const ALL: [ParamKind; 4] = [ParamKind::A, ParamKind::D, ParamKind::Alpha, ParamKind::Theta];

    /// Short name used in reports (`a`, `d`, `alpha`, `theta`).
    pub const fn name(self) -> &'static str {
        match self {
            ParamKind::A => "a",
            ParamKind::D => "d",
            ParamKind::Alpha => "alpha",
            ParamKind::Theta => "theta",
        }
    }

    /// Whether the parameter is an angle (α, θ offset): bounds compare it modulo 2π.
    pub const fn is_angle(self) -> bool {
        matches!(self, ParamKind::Alpha | ParamKind::Theta)
    }

    /// Index of parameter (`self`, `joint`) in a chain of `n` joints.
    pub const fn index(self, joint: usize, n: usize) -> usize {
        self as usize * n + joint
    }

    /// Kind and joint (0-based) of parameter `index` in a chain of `n` joints.
    pub const fn of_index(index: usize, n: usize) -> (ParamKind, usize) {
        let kind = match index / n {
            0 => ParamKind::A,
            1 => ParamKind::D,
            2 => ParamKind::Alpha,
            _ => ParamKind::Theta,
        };
        (kind, index % n)
    }
}

/// A rigid transform kept as rotation matrix + translation (cheaper than quaternions in FK).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Rotation (columns are the frame's axes in the parent frame).
    pub r: Matrix3<f64>,
    /// Origin in the parent frame.
    pub p: Vector3<f64>,
}

impl Frame {
    /// The identity transform.
    pub fn identity() -> Self {
        Frame {
            r: Matrix3::identity(),
            p: Vector3::zeros(),
        }
    }

    /// `self · other`.
    pub fn compose(&self, other: &Frame) -> Frame {
        Frame {
            r: self.r * other.r,
            p: self.r * other.p + self.p,
        }
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Frame {
        let rt = self.r.transpose();
        Frame {
            r: rt,
            p: -(rt * self.p),
        }
    }

    /// Converts to a nalgebra isometry (the rotation is re-orthonormalised).
    pub fn to_isometry(&self) -> Isometry3<f64> {
        let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&self.r));
        Isometry3::from_parts(Translation3::from(self.p), rot)
    }

    /// Converts from a nalgebra isometry.
    pub fn from_isometry(iso: &Isometry3<f64>) -> Frame {
        Frame {
            r: iso.rotation.to_rotation_matrix().into_inner(),
            p: iso.translation.vector,
        }
    }

    /// From a 4 × 4 homogeneous matrix (the bottom row is ignored; the rotation is taken as is).
    pub fn from_matrix4(m: &Matrix4<f64>) -> Frame {
        Frame {
            r: m.fixed_view::<3, 3>(0, 0).into_owned(),
            p: m.fixed_view::<3, 1>(0, 3).into_owned(),
        }
    }

    /// To a 4 × 4 homogeneous matrix.
    pub fn to_matrix4(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.r);
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.p);
        m
    }

    /// True when every entry is finite.
    pub fn is_finite(&self) -> bool {
        self.r.iter().chain(self.p.iter()).all(|x| x.is_finite())
    }
}

impl DhRow {
    /// The link transform of eq. (1) for joint variable `q` (the offset is added here).
    pub fn transform(&self, q: f64) -> Frame {
        let (sa, ca) = libm::sincos(self.alpha);
        self.transform_with(q, sa, ca)
    }

    /// The row's motion about its joint, `Rz(q + θ)`: the first factor of
    /// [`DhRow::transform`], which is `joint(q) · tail()`.
    pub fn joint(&self, q: f64) -> Frame {
        let (st, ct) = libm::sincos(q + self.theta_offset);
        Frame {
            r: Matrix3::new(ct, -st, 0.0, st, ct, 0.0, 0.0, 0.0, 1.0),
            p: Vector3::zeros(),
        }
    }

    /// The row's fixed part, `Tz(d) Tx(a) Rx(α)`: where the next joint's axis sits in the frame
    /// that turned with this joint (the second factor of [`DhRow::transform`]).
    pub fn tail(&self) -> Frame {
        let (sa, ca) = libm::sincos(self.alpha);
        Frame {
            r: Matrix3::new(1.0, 0.0, 0.0, 0.0, ca, -sa, 0.0, sa, ca),
            p: Vector3::new(self.a, 0.0, self.d),
        }
    }

    /// [`DhRow::transform`] with `(sin α, cos α)` given (they are constant per table, while the
    /// joint angle changes with every sample).
    #[inline]
    fn transform_with(&self, q: f64, sa: f64, ca: f64) -> Frame {
        let (st, ct) = libm::sincos(q + self.theta_offset);
        Frame {
            r: Matrix3::new(ct, -st * ca, st * sa, st, ct * ca, -ct * sa, 0.0, sa, ca),
            p: Vector3::new(self.a * ct, self.a * st, self.d),
        }
    }

    /// `T(q) · u`, the link transform composed with the pose `u` of the tool in the next frame,
    /// without forming `T`: its third row is `(0, sin α, cos α)`, whose zero takes no work.
    /// Bit-identical to `self.transform_with(q, sa, ca).compose(u)` (a product by that zero
    /// adds an exact zero there), at two thirds of its multiplications in that row.
    #[inline]
    fn then(&self, q: f64, sa: f64, ca: f64, u: &Frame) -> Frame {
        let (st, ct) = libm::sincos(q + self.theta_offset);
        let (r0, r1) = ([ct, -st * ca, st * sa], [st, ct * ca, -ct * sa]);
        let ur = &u.r;
        let dot = |t: &[f64; 3], j: usize| t[0] * ur[(0, j)] + t[1] * ur[(1, j)] + t[2] * ur[(2, j)];
        let last = |j: usize| sa * ur[(1, j)] + ca * ur[(2, j)];
        let dot_p = |t: &[f64; 3]| t[0] * u.p.x + t[1] * u.p.y + t[2] * u.p.z;
        Frame {
            r: Matrix3::new(
                dot(&r0, 0),
                dot(&r0, 1),
                dot(&r0, 2),
                dot(&r1, 0),
                dot(&r1, 1),
                dot(&r1, 2),
                last(0),
                last(1),
                last(2),
            ),
            p: Vector3::new(
                dot_p(&r0) + self.a * ct,
                dot_p(&r1) + self.a * st,
                (sa * u.p.y + ca * u.p.z) + self.d,
            ),
        }
    }

    /// Value of parameter `kind`.
    pub fn get(&self, kind: ParamKind) -> f64 {
        match kind {
            ParamKind::A => self.a,
            ParamKind::D => self.d,
            ParamKind::Alpha => self.alpha,
            ParamKind::Theta => self.theta_offset,
        }
    }

    /// Mutable access to parameter `kind`.
    pub fn get_mut(&mut self, kind: ParamKind) -> &mut f64 {
        match kind {
            ParamKind::A => &mut self.a,
            ParamKind::D => &mut self.d,
            ParamKind::Alpha => &mut self.alpha,
            ParamKind::Theta => &mut self.theta_offset,
        }
    }
}

/// A D-H table of `N` joints.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DhTable<const N: usize> {
    /// Rows, joint 1 first.
    pub rows: [DhRow; N],
}

const DEG: f64 = core::f64::consts::PI / 180.0;

fn paper_table(a: [f64; 7], alpha_deg: [f64; 7], d: [f64; 7]) -> DhTable<7> {
    let offsets_deg = [0.0, 90.0, 0.0, 0.0, 0.0, 90.0, 0.0];
    let mut rows = [DhRow {
        a: 0.0,
        alpha: 0.0,
        d: 0.0,
        theta_offset: 0.0,
    }; 7];
    for (i, row) in rows.iter_mut().enumerate() {
        *row = DhRow {
            a: a[i],
            alpha: alpha_deg[i] * DEG,
            d: d[i],
            theta_offset: offsets_deg[i] * DEG,
        };
    }
    DhTable { rows }
}

impl DhTable<7> {
    /// The paper's Table 1 (nominal suit). `α_1 = 270°` is stored as `−90°` (paper note 5).
    pub fn paper_nominal() -> Self {
        paper_table(
            [0.04, 0.04, 0.431, 0.244, 0.0, 0.0, 0.0],
            [-90.0, 90.0, 90.0, -90.0, 90.0, 90.0, 90.0],
            [0.0; 7],
        )
    }

    /// The paper's Table 4 (the hypothetical "actual" arm of Section 4).
    pub fn paper_actual() -> Self {
        paper_table(
            [0.03, 0.05, 0.401, 0.264, 0.02, 0.01, 0.0],
            [-90.0, 93.0, 90.0, -95.0, 90.0, 92.0, 90.0],
            [0.03, 0.02, 0.0, 0.0, 0.01, 0.0, 0.0],
        )
    }
}

impl<const N: usize> DhTable<N> {
    /// The arm of the first `M` joints of this one (`M ≤ N`, checked at compile time): its
    /// first `M` rows, the chain ending at joint `M`'s frame.
    pub fn first<const M: usize>(&self) -> DhTable<M> {
        const { assert!(M <= N, "an arm of at most N joints") };
        DhTable {
            rows: core::array::from_fn(|j| self.rows[j]),
        }
    }

    /// Number of parameters of this table (`4N`).
    pub const PARAMS: usize = 4 * N;

    /// Parameter `index` (see the module docs for the ordering).
    pub fn param(&self, index: usize) -> f64 {
        let (kind, joint) = ParamKind::of_index(index, N);
        self.rows[joint].get(kind)
    }

    /// Mutable parameter `index`.
    pub fn param_mut(&mut self, index: usize) -> &mut f64 {
        let (kind, joint) = ParamKind::of_index(index, N);
        self.rows[joint].get_mut(kind)
    }

    /// Returns a copy with `delta` (in parameter order, length `4N`) added.
    pub fn perturbed(&self, delta: &[f64]) -> Self {
        let mut out = *self;
        for (i, d) in delta.iter().enumerate().take(4 * N) {
            *out.param_mut(i) += d;
        }
        out
    }

    /// Returns a copy with `delta[j]` added to the θ offset of joint `j`.
    pub fn with_theta_offsets(&self, delta: &[f64; N]) -> Self {
        let mut out = *self;
        for (row, d) in out.rows.iter_mut().zip(delta) {
            row.theta_offset += d;
        }
        out
    }

    /// True when every entry is finite.
    pub fn is_finite(&self) -> bool {
        self.rows
            .iter()
            .all(|r| r.a.is_finite() && r.d.is_finite() && r.alpha.is_finite() && r.theta_offset.is_finite())
    }

    /// Forward kinematics (eq. 1): tool frame in the base frame.
    pub fn fk(&self, joints: &[f64; N]) -> Frame {
        let mut t = Frame::identity();
        for (row, q) in self.rows.iter().zip(joints) {
            t = t.compose(&row.transform(*q));
        }
        t
    }

    /// The arm as a URDF or a transform tree draws it, at joint readings `joints`: link `i`'s
    /// frame in its parent's (the base's for the first) is the parent row's
    /// [`DhRow::tail`] then this row's [`DhRow::joint`], and the tool's frame in the last
    /// link's is the last row's tail. Composed in order they are [`DhTable::fk`]; at zero
    /// readings they are the URDF's fixed joint origins. This is the one place the D-H rows
    /// are split at the joints: the log's transforms and the URDF export both read it.
    pub fn links(&self, joints: &[f64; N]) -> ([Frame; N], Frame) {
        let mut links = [Frame::identity(); N];
        let mut parent = Frame::identity();
        for ((link, row), &q) in links.iter_mut().zip(&self.rows).zip(joints) {
            *link = parent.compose(&row.joint(q));
            parent = row.tail();
        }
        (links, parent)
    }

    /// The table with `sin α`, `cos α` of every row evaluated once, for kinematics over many
    /// samples (the results are bit-identical to [`DhTable::fk_jacobian`] and, for
    /// [`PreparedTable::frames`], to [`DhTable::fk`]).
    pub fn prepare(&self) -> PreparedTable<N> {
        PreparedTable {
            rows: self.rows,
            trig: core::array::from_fn(|i| libm::sincos(self.rows[i].alpha)),
        }
    }

    /// Forward kinematics and the analytic identification Jacobian.
    ///
    /// Returns the tool pose and `cols[kind][joint]`, the tool-frame twist `[v; ω]` of a unit
    /// change of parameter (`kind`, `joint`). `cols[ParamKind::Theta as usize]` is the joint
    /// Jacobian (∂pose/∂q, also in the tool frame).
    pub fn fk_jacobian(&self, joints: &[f64; N]) -> (Frame, [[Vector6<f64>; N]; 4]) {
        self.prepare().fk_jacobian(joints)
    }

    /// The joint Jacobian (6 × N, tool frame): column `j` is ∂pose/∂q_j.
    pub fn joint_jacobian(&self, joints: &[f64; N]) -> [Vector6<f64>; N] {
        self.fk_jacobian(joints).1[ParamKind::Theta as usize]
    }
}

/// A [`DhTable`] with the trigonometry of its constant twists `α` precomputed (see
/// [`DhTable::prepare`]): per sample only `sin`/`cos` of the joint angles remain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreparedTable<const N: usize> {
    rows: [DhRow; N],
    /// `(sin α_i, cos α_i)`.
    trig: [(f64, f64); N],
}

impl<const N: usize> PreparedTable<N> {
    /// The frames after joints 1..=`n` in the base frame (index `i`: after joint `i + 1`) for
    /// the angles `joints[..n]`, composed from the base as [`DhTable::fk`] does (bit-identical
    /// to it for `n = N`); the frames past `n` are the identity. What an IMU on link `i` sees,
    /// without the links past it.
    pub fn frames(&self, joints: &[f64], n: usize) -> [Frame; N] {
        let mut out = [Frame::identity(); N];
        let mut t = Frame::identity();
        for i in 0..n.min(N).min(joints.len()) {
            let (sa, ca) = self.trig[i];
            t = t.compose(&self.rows[i].transform_with(joints[i], sa, ca));
            out[i] = t;
        }
        out
    }

    /// The tool pose, composed from the tool backwards like [`PreparedTable::fk_jacobian`]
    /// does (so bit-identical to its pose, which [`DhTable::fk`] is not), without the Jacobian.
    pub(crate) fn pose(&self, joints: &[f64; N]) -> Frame {
        let mut u = Frame::identity();
        for i in (0..N).rev() {
            let (sa, ca) = self.trig[i];
            u = self.rows[i].then(joints[i], sa, ca, &u);
        }
        u
    }

    /// [`DhTable::fk_jacobian`].
    pub(crate) fn fk_jacobian(&self, joints: &[f64; N]) -> (Frame, [[Vector6<f64>; N]; 4]) {
        let mut cols = [[Vector6::zeros(); N]; 4];
        let u = self.fk_jacobian_into(joints, &mut cols);
        (u, cols)
    }

    /// [`PreparedTable::fk_jacobian`] into a caller's buffer (no copy of the 4N columns).
    pub(crate) fn fk_jacobian_into(&self, joints: &[f64; N], cols: &mut [[Vector6<f64>; N]; 4]) -> Frame {
        // Backward pass: `u` is U_{i+1} = T_{i+1} ⋯ T_N, the pose of the tool in frame i.
        let mut u = Frame::identity();
        for i in (0..N).rev() {
            let row = &self.rows[i];
            let (sa, ca) = self.trig[i];
            // Local twists (v, ω) in frame i (post-multiplied), see paper notes 1-2:
            // a: (x, 0), d: (z, 0), α: (0, x), θ: ((0, a cos α, −a sin α), z); in the tool frame
            // v' = Uᵀ(ω × p + v), ω' = Uᵀω. With x = (1, 0, 0) and z = (0, sin α, cos α), the
            // zero and unit entries are left out: every product by them was exact, so the
            // columns are bit-identical to the general products `Uᵀ x`, `Uᵀ (x × p)`, ….
            let (r, p) = (&u.r, &u.p);
            // Uᵀ v for v = (0, v1, v2).
            let rt_yz = |v1: f64, v2: f64| {
                Vector3::new(
                    r[(1, 0)] * v1 + r[(2, 0)] * v2,
                    r[(1, 1)] * v1 + r[(2, 1)] * v2,
                    r[(1, 2)] * v1 + r[(2, 2)] * v2,
                )
            };
            let x_t = Vector3::new(r[(0, 0)], r[(0, 1)], r[(0, 2)]);
            let z_t = rt_yz(sa, ca);
            // x × p = (0, −p_z, p_y).
            let v_alpha = rt_yz(-p.z, p.y);
            // z × p + (0, a cos α, −a sin α).
            let w = Vector3::new(sa * p.z - ca * p.y, ca * p.x + row.a * ca, -(sa * p.x) - row.a * sa);
            let v_theta = r.transpose() * w;
            cols[0][i] = Vector6::new(x_t.x, x_t.y, x_t.z, 0.0, 0.0, 0.0);
            cols[1][i] = Vector6::new(z_t.x, z_t.y, z_t.z, 0.0, 0.0, 0.0);
            cols[2][i] = Vector6::new(v_alpha.x, v_alpha.y, v_alpha.z, x_t.x, x_t.y, x_t.z);
            cols[3][i] = Vector6::new(v_theta.x, v_theta.y, v_theta.z, z_t.x, z_t.y, z_t.z);
            u = row.then(joints[i], sa, ca, &u);
        }
        u
    }
}

/// `[x]×`, the cross-product matrix.
pub fn skew(x: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -x.z, x.y, x.z, 0.0, -x.x, -x.y, x.x, 0.0)
}

/// Rotation vector (axis · angle) of a rotation matrix, accurate for tiny and near-π angles.
pub fn log_so3(r: &Matrix3<f64>) -> Vector3<f64> {
    let v = 0.5 * Vector3::new(r[(2, 1)] - r[(1, 2)], r[(0, 2)] - r[(2, 0)], r[(1, 0)] - r[(0, 1)]);
    let s = v.norm();
    let c = 0.5 * (r.trace() - 1.0);
    let th = libm::atan2(s, c);
    if th < 1e-3 {
        // θ/sin θ = 1 + θ²/6 + O(θ⁴)
        return v * (1.0 + th * th / 6.0);
    }
    if th < core::f64::consts::PI - 1e-3 {
        return v * (th / s);
    }
    // Near π: (R + Rᵀ)/2 = c·I + (1 − c)·a aᵀ; take the dominant column of a aᵀ, signed by v.
    let b = (0.5 * (r + r.transpose()) - c * Matrix3::identity()) / (1.0 - c);
    let i = (0..3).max_by(|&x, &y| b[(x, x)].total_cmp(&b[(y, y)])).unwrap_or(0);
    let mut a: Vector3<f64> = b.column(i).into_owned() / libm::sqrt(b[(i, i)].max(1e-300));
    if a.dot(&v) < 0.0 {
        a = -a;
    }
    a.normalize() * th
}

/// The pose error `e = [R_mᵀ (p_a − p_m); log(R_mᵀ R_a)]` of `actual` against `model`, in the
/// model's tool frame (see the module docs).
pub fn pose_error(model: &Frame, actual: &Frame) -> Vector6<f64> {
    let rt = model.r.transpose();
    let p = rt * (actual.p - model.p);
    let w = log_so3(&(rt * actual.r));
    Vector6::new(p.x, p.y, p.z, w.x, w.y, w.z)
}

/// The matrix `M(e)` with `pose_error(M·exp(ξ), A) ≈ e − M(e) ξ` for a tool-frame twist ξ.
///
/// At `e = 0` it is the identity; using `M(e)·J` as the residual Jacobian makes Gauss-Newton
/// exact to first order even when the residual is not small.
pub fn error_jacobian(e: &Vector6<f64>) -> Matrix6<f64> {
    let ep = Vector3::new(e[0], e[1], e[2]);
    let er = Vector3::new(e[3], e[4], e[5]);
    let mut m = Matrix6::identity();
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(&ep)));
    let th = er.norm();
    let k = skew(&er);
    let c = if th < 1e-4 {
        1.0 / 12.0 + th * th / 720.0
    } else {
        let (s, c) = libm::sincos(th);
        1.0 / (th * th) - (1.0 + c) / (2.0 * th * s)
    };
    let jl_inv = Matrix3::identity() - 0.5 * k + c * k * k;
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&jl_inv);
    m
}

/// Anatomical bounds on the geometry (Table 2). `None` means unbounded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds<const N: usize> {
    /// `[min, max]` per parameter, in parameter order (`kind · N + joint`).
    pub limits: [[Option<(f64, f64)>; N]; 4],
}

impl<const N: usize> Bounds<N> {
    /// No bounds at all.
    pub fn none() -> Self {
        Bounds { limits: [[None; N]; 4] }
    }
}

impl Bounds<7> {
    /// The paper's Table 2: only `a_1 … a_4` are bounded (metres).
    pub fn paper() -> Self {
        let mut b = Self::none();
        let a = [(0.02, 0.06), (0.02, 0.06), (0.377, 0.485), (0.211, 0.267)];
        for (j, lim) in a.iter().enumerate() {
            b.limits[ParamKind::A as usize][j] = Some(*lim);
        }
        b
    }
}

/// A parameter outside its [`Bounds`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoundViolation {
    /// Which parameter.
    pub kind: ParamKind,
    /// Joint, 0-based.
    pub joint: usize,
    /// Its value.
    pub value: f64,
    /// The violated interval.
    pub min: f64,
    /// The violated interval.
    pub max: f64,
}

/// `value` as bounds compare it: angles are brought within π of the interval's centre (so
/// `[-190°, -170°]` holds 175°), lengths are left as they are.
fn bounded_value(kind: ParamKind, value: f64, (min, max): (f64, f64)) -> f64 {
    if !kind.is_angle() {
        return value;
    }
    let centre = 0.5 * (min + max);
    let tau = 2.0 * core::f64::consts::PI;
    let d = libm::remainder(value - centre, tau);
    centre + d
}

/// Every parameter of `table` outside its [`Bounds`], in parameter order (a non-finite value is
/// outside any interval). Angles are compared modulo 2π, see [`ParamKind::is_angle`].
pub fn bound_violations<'a, const N: usize>(
    table: &'a DhTable<N>,
    bounds: &'a Bounds<N>,
) -> impl Iterator<Item = BoundViolation> + 'a {
    ParamKind::ALL.into_iter().flat_map(move |kind| {
        (0..N).filter_map(move |j| {
            let (min, max) = bounds.limits[kind as usize][j]?;
            let value = table.rows[j].get(kind);
            let v = bounded_value(kind, value, (min, max));
            (!(min..=max).contains(&v)).then_some(BoundViolation {
                kind,
                joint: j,
                value,
                min,
                max,
            })
        })
    })
}

/// Checks `table` against `bounds`; the first violation (in parameter order) is returned.
pub fn check_bounds<const N: usize>(table: &DhTable<N>, bounds: &Bounds<N>) -> Result<(), BoundViolation> {
    bound_violations(table, bounds).next().map_or(Ok(()), Err)
}

/// Clamps every bounded parameter of `table` into its interval (angles modulo 2π, as
/// [`bound_violations`] compares them); returns how many were moved.
pub fn clamp_to_bounds<const N: usize>(table: &mut DhTable<N>, bounds: &Bounds<N>) -> usize {
    let mut moved = 0;
    for kind in ParamKind::ALL {
        for j in 0..N {
            if let Some((min, max)) = bounds.limits[kind as usize][j] {
                let v = table.rows[j].get_mut(kind);
                let b = bounded_value(kind, *v, (min, max));
                if !(min..=max).contains(&b) {
                    *v = b.clamp(min, max);
                    moved += 1;
                }
            }
        }
    }
    moved
}

/// Joint ranges (rad), `[min, max]` per joint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointRanges<const N: usize> {
    /// `[min, max]` per joint (rad).
    pub limits: [(f64, f64); N],
}

/// Irrational steps (fractional parts of √2, √3, √5, …) of the additive recurrence that spreads
/// points evenly over a box: joint `j` of point `i` at `frac((i + ½) · SPREAD[j])`.
const SPREAD: [f64; 8] = [
    0.414_213_562_373_095,
    0.732_050_807_568_877,
    0.236_067_977_499_790,
    0.645_751_311_064_591,
    0.316_624_790_355_400,
    0.605_551_275_463_989,
    0.123_105_625_617_661,
    0.358_898_943_540_674,
];

/// Point `i` of the recurrence, coordinate `j`, in `[0, 1)`.
fn spread(i: usize, j: usize) -> f64 {
    let x = (i as f64 + 0.5) * SPREAD[j % SPREAD.len()] + (j / SPREAD.len()) as f64 * 0.5;
    x - libm::floor(x)
}

impl<const N: usize> JointRanges<N> {
    /// The ranges of the first `M` joints (`M ≤ N`, checked at compile time), for
    /// [`DhTable::first`].
    pub fn first<const M: usize>(&self) -> JointRanges<M> {
        const { assert!(M <= N, "an arm of at most N joints") };
        JointRanges {
            limits: core::array::from_fn(|j| self.limits[j]),
        }
    }

    /// Point `i` of a set spread evenly over the ranges (joint `j` at `frac((i + ½) · s_j)` of
    /// its range, `s_j` the fractional parts of √2, √3, √5, …: an additive recurrence, so any
    /// first `n` points cover the box about evenly). What "the poses a wearer will take" means
    /// where a session's own poses are not enough ([`crate::ErrorPoses::Ranges`], guidance).
    pub fn spread(&self, i: usize) -> [f64; N] {
        core::array::from_fn(|j| self.spread_joint(i, j))
    }

    /// Joint `j`'s angle in point `i` of [`JointRanges::spread`].
    pub fn spread_joint(&self, i: usize, j: usize) -> f64 {
        let (lo, hi) = self.limits[j];
        lo + (hi - lo) * spread(i, j)
    }
}

impl JointRanges<7> {
    /// The paper's Table 3, with paper note 5 (θ5 ∈ [−20°, 30°], θ6 ∈ [−30°, 40°]).
    pub fn paper() -> Self {
        let deg = [
            (-90.0, 90.0),
            (-120.0, 30.0),
            (-10.0, 100.0),
            (0.0, 150.0),
            (-20.0, 30.0),
            (-30.0, 40.0),
            (-90.0, 90.0),
        ];
        let mut limits = [(0.0, 0.0); 7];
        for (l, (lo, hi)) in limits.iter_mut().zip(deg) {
            *l = (lo * DEG, hi * DEG);
        }
        JointRanges { limits }
    }
}

/// One calibration sample: reported joint angles and the measured tool pose (base frame).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample<const N: usize> {
    /// Reported joint angles (rad), without the D-H offsets.
    pub joints: [f64; N],
    /// Measured tool pose in the base frame.
    pub pose: Frame,
}

impl<const N: usize> Sample<N> {
    /// A sample from joint angles and a nalgebra isometry.
    pub fn from_isometry(joints: [f64; N], pose: &Isometry3<f64>) -> Self {
        Sample {
            joints,
            pose: Frame::from_isometry(pose),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rand_joints(seed: u64) -> [f64; 7] {
        let mut rng = crate::rng::Rng::new(seed);
        let r = JointRanges::paper();
        core::array::from_fn(|j| r.limits[j].0 + (r.limits[j].1 - r.limits[j].0) * rng.uniform())
    }

    #[test]
    fn the_links_compose_to_the_forward_kinematics() {
        let table = DhTable::paper_actual();
        for seed in 0..20 {
            let q = rand_joints(seed);
            let (links, tool) = table.links(&q);
            let composed = links.iter().fold(Frame::identity(), |t, l| t.compose(l)).compose(&tool);
            let fk = table.fk(&q);
            assert!((composed.p - fk.p).norm() < 1e-12 && (composed.r - fk.r).norm() < 1e-12);
            for (row, &qi) in table.rows.iter().zip(&q) {
                let split = row.joint(qi).compose(&row.tail());
                let whole = row.transform(qi);
                assert!((split.p - whole.p).norm() < 1e-12 && (split.r - whole.r).norm() < 1e-12);
            }
        }
        // The first link turns at the base; every other sits at its parent row's tail.
        let (links, tool) = table.links(&[0.0; 7]);
        assert_eq!(links[0].p, Vector3::zeros());
        let r = &table.rows[2];
        assert_eq!(links[3].p, Vector3::new(r.a, 0.0, r.d));
        assert_eq!(tool.p, Vector3::new(table.rows[6].a, 0.0, table.rows[6].d));
    }

    /// The kinematics with every product written out in general (`Uᵀ x`, `x × p`, `T · U`), as
    /// they were before the zero and unit entries were left out.
    fn fk_jacobian_general(t: &PreparedTable<7>, joints: &[f64; 7]) -> (Frame, [[Vector6<f64>; 7]; 4]) {
        let mut cols = [[Vector6::zeros(); 7]; 4];
        let mut u = Frame::identity();
        for i in (0..7).rev() {
            let row = &t.rows[i];
            let (sa, ca) = t.trig[i];
            let ex = Vector3::new(1.0, 0.0, 0.0);
            let z_local = Vector3::new(0.0, sa, ca);
            let rt = u.r.transpose();
            let x_t = rt * ex;
            let z_t = rt * z_local;
            let v_alpha = rt * ex.cross(&u.p);
            let v_theta = rt * (z_local.cross(&u.p) + Vector3::new(0.0, row.a * ca, -row.a * sa));
            cols[0][i] = Vector6::new(x_t.x, x_t.y, x_t.z, 0.0, 0.0, 0.0);
            cols[1][i] = Vector6::new(z_t.x, z_t.y, z_t.z, 0.0, 0.0, 0.0);
            cols[2][i] = Vector6::new(v_alpha.x, v_alpha.y, v_alpha.z, x_t.x, x_t.y, x_t.z);
            cols[3][i] = Vector6::new(v_theta.x, v_theta.y, v_theta.z, z_t.x, z_t.y, z_t.z);
            u = row.transform_with(joints[i], sa, ca).compose(&u);
        }
        (u, cols)
    }

    /// `sincos` is `sin` and `cos` in one call (the same kernels after one range reduction).
    #[test]
    fn sincos_is_sin_and_cos_bit_for_bit() {
        let mut rng = crate::rng::Rng::new(5);
        for _ in 0..100_000 {
            let x = 8.0 * (rng.uniform() - 0.5) * libm::exp(-10.0 * rng.uniform());
            let (s, c) = libm::sincos(x);
            assert_eq!(
                (s.to_bits(), c.to_bits()),
                (libm::sin(x).to_bits(), libm::cos(x).to_bits()),
                "x = {x:e}"
            );
        }
    }

    /// Leaving out the products by the zero and unit entries changed no bit of any result (a
    /// zero's sign aside, which `==` ignores): the pushed tables stay what they were.
    #[test]
    fn kinematics_without_the_trivial_products_are_bit_identical() {
        let mut rng = crate::rng::Rng::new(11);
        for seed in 0..2_000u64 {
            let mut table = DhTable::paper_nominal();
            for row in table.rows.iter_mut() {
                row.a += 0.01 * rng.normal();
                row.d += 0.01 * rng.normal();
                row.alpha += 0.02 * rng.normal();
                row.theta_offset += 0.02 * rng.normal();
            }
            let t = table.prepare();
            let q = rand_joints(seed);
            let (u, cols) = t.fk_jacobian(&q);
            let (u0, cols0) = fk_jacobian_general(&t, &q);
            assert!(u.r == u0.r && u.p == u0.p, "pose, seed {seed}");
            assert!(cols == cols0, "Jacobian, seed {seed}");
            let pose = t.pose(&q);
            assert!(pose.r == u0.r && pose.p == u0.p, "pose alone, seed {seed}");
        }
    }

    #[test]
    fn row_matches_eq1_composition() {
        let row = DhRow {
            a: 0.3,
            alpha: 0.7,
            d: 0.1,
            theta_offset: 0.2,
        };
        let t = row.transform(0.5);
        let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), 0.7);
        let rx = Rotation3::from_axis_angle(&Vector3::x_axis(), 0.7);
        let expect_r = rz.matrix() * rx.matrix();
        assert!((t.r - expect_r).norm() < 1e-15);
        assert!((t.p - Vector3::new(0.3 * libm::cos(0.7), 0.3 * libm::sin(0.7), 0.1)).norm() < 1e-15);
    }

    #[test]
    fn identification_jacobian_matches_finite_differences() {
        for seed in 0..5 {
            let table = DhTable::paper_actual();
            let q = rand_joints(seed);
            let (t0, cols) = table.fk_jacobian(&q);
            for p in 0..28 {
                let h = 1e-6;
                let mut delta = [0.0; 28];
                delta[p] = h;
                let tp = table.perturbed(&delta).fk(&q);
                delta[p] = -h;
                let tm = table.perturbed(&delta).fk(&q);
                let fd = (pose_error(&t0, &tp) - pose_error(&t0, &tm)) / (2.0 * h);
                let (k, j) = ParamKind::of_index(p, 7);
                let an = cols[k as usize][j];
                assert!((fd - an).norm() < 1e-8, "param {p}: fd {fd:?} analytic {an:?}");
            }
        }
    }

    #[test]
    fn joint_jacobian_matches_finite_differences() {
        let table = DhTable::paper_nominal();
        let q = rand_joints(9);
        let (t0, _) = table.fk_jacobian(&q);
        let jj = table.joint_jacobian(&q);
        for j in 0..7 {
            let mut qp = q;
            let mut qm = q;
            qp[j] += 1e-6;
            qm[j] -= 1e-6;
            let fd = (pose_error(&t0, &table.fk(&qp)) - pose_error(&t0, &table.fk(&qm))) / 2e-6;
            assert!((fd - jj[j]).norm() < 1e-8, "joint {j}");
        }
    }

    #[test]
    fn residual_jacobian_is_exact_away_from_zero_error() {
        // e(θ) = pose_error(fk(table+θ), A) with A far from the model: de/dθ = −M(e) J.
        let model = DhTable::paper_nominal();
        let actual = DhTable::paper_actual().fk(&rand_joints(3));
        let q = rand_joints(4);
        let (t0, cols) = model.fk_jacobian(&q);
        let e0 = pose_error(&t0, &actual);
        assert!(e0.norm() > 0.05);
        let m = error_jacobian(&e0);
        for p in 0..28 {
            let mut delta = [0.0; 28];
            delta[p] = 1e-6;
            let ep = pose_error(&model.perturbed(&delta).fk(&q), &actual);
            delta[p] = -1e-6;
            let em = pose_error(&model.perturbed(&delta).fk(&q), &actual);
            let fd = (ep - em) / 2e-6;
            let (k, j) = ParamKind::of_index(p, 7);
            let an = -(m * cols[k as usize][j]);
            assert!((fd - an).norm() < 1e-7, "param {p}: {fd:?} vs {an:?}");
        }
    }

    #[test]
    fn frames_end_at_fk_bit_for_bit_and_stop_where_asked() {
        let table = DhTable::paper_actual();
        let prepared = table.prepare();
        for seed in 0..20 {
            let q = rand_joints(seed);
            let frames = prepared.frames(&q, 7);
            assert_eq!(frames[6], table.fk(&q));
            let first: [f64; 3] = [q[0], q[1], q[2]];
            let head = prepared.frames(&first, 7);
            assert_eq!(head[..3], frames[..3]);
            assert_eq!(head[3], Frame::identity());
            assert_eq!(prepared.frames(&q, 2)[2], Frame::identity());
        }
    }

    #[test]
    fn log_so3_is_accurate_over_the_whole_range() {
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        for th in [1e-9, 1e-6, 1e-3, 0.5, 2.0, 3.1, core::f64::consts::PI - 1e-5] {
            let r = Rotation3::new(axis * th).into_inner();
            let w = log_so3(&r);
            assert!((w - axis * th).norm() < 1e-9 * th.max(1e-3), "θ = {th}: {w:?}");
        }
    }

    #[test]
    fn pose_error_is_zero_for_equal_poses_and_isometry_round_trips() {
        let t = DhTable::paper_actual().fk(&rand_joints(1));
        assert!(pose_error(&t, &t).norm() < 1e-12);
        let back = Frame::from_isometry(&t.to_isometry());
        assert!((back.r - t.r).norm() < 1e-12 && (back.p - t.p).norm() < 1e-15);
        assert_eq!(Frame::from_matrix4(&t.to_matrix4()), t);
        let s = Sample::from_isometry([0.0; 7], &t.to_isometry());
        assert!(pose_error(&s.pose, &t).norm() < 1e-12);
    }

    #[test]
    fn bounds_check_and_clamp() {
        let b = Bounds::paper();
        assert_eq!(check_bounds(&DhTable::paper_actual(), &b), Ok(()));
        let mut t = DhTable::paper_nominal();
        t.rows[2].a = 0.5;
        let v = check_bounds(&t, &b).unwrap_err();
        assert_eq!((v.kind, v.joint), (ParamKind::A, 2));
        assert_eq!(clamp_to_bounds(&mut t, &b), 1);
        assert_eq!(t.rows[2].a, 0.485);
        assert_eq!(check_bounds(&t, &b), Ok(()));
    }

    #[test]
    fn every_violation_is_listed_and_angles_compare_modulo_two_pi() {
        let deg = core::f64::consts::PI / 180.0;
        let mut b = Bounds::paper();
        // α1 within 5° of 180°: -178° is 2° away, 170° is 10° away.
        b.limits[ParamKind::Alpha as usize][0] = Some((175.0 * deg, 185.0 * deg));
        let mut t = DhTable::paper_actual();
        t.rows[0].alpha = -178.0 * deg;
        assert_eq!(check_bounds(&t, &b), Ok(()));
        t.rows[0].alpha = 170.0 * deg;
        t.rows[1].a = f64::NAN;
        t.rows[3].a = 1.0;
        let v: heapless::Vec<BoundViolation, 8> = bound_violations(&t, &b).collect();
        let which: heapless::Vec<(ParamKind, usize), 8> = v.iter().map(|v| (v.kind, v.joint)).collect();
        assert_eq!(which, [(ParamKind::A, 1), (ParamKind::A, 3), (ParamKind::Alpha, 0)]);
        t.rows[1].a = 0.04; // a NaN has no nearest bound
        assert_eq!(clamp_to_bounds(&mut t, &b), 2);
        assert!((t.rows[0].alpha - 175.0 * deg).abs() < 1e-12);
        assert_eq!(check_bounds(&t, &b), Ok(()));
    }

    #[test]
    fn param_indexing_round_trips() {
        let mut t = DhTable::paper_nominal();
        for p in 0..28 {
            let (k, j) = ParamKind::of_index(p, 7);
            assert_eq!(k.index(j, 7), p);
            *t.param_mut(p) = p as f64;
            assert_eq!(t.rows[j].get(k), p as f64);
        }
    }
}
