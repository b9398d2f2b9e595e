//! The assembled model: coordinate layout, constraints, mass matrix and forces, all
//! read from a [`Scene`] once and immutable afterwards.
//!
//! q holds the x, y of every free point in scene order, then the relative
//! coordinates. Fixed points are constants, not coordinates.

pub mod constraints;
pub mod forces;
pub mod mass;
pub mod parameters;
pub mod plausibility;

use crate::error::{Error, Result};
use crate::scene::{self, ConstraintKind, Effect, RelativeKind, Scene};
use constraints::Equation;
pub use constraints::MAX_LOCAL;
use forces::Force;
use nalgebra::{DMatrix, DVector};

/// Where a point's coordinates live: in q (index of its x) or fixed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PointSlot {
    Free(usize),
    Fixed([f64; 2]),
}

/// One scalar constraint of the model, with its local coordinates.
#[derive(Debug, Clone)]
pub struct Constraint {
    pub name: String,
    pub equation: Equation,
    /// The scene points of its local coordinates, in order (two entries of u each).
    pub points: Vec<usize>,
    /// The body whose rigidity it states, if any.
    pub body: Option<usize>,
    /// The scene coordinate (index in `scene.coordinates`) it defines, if any.
    pub coordinate: Option<usize>,
    /// For each local coordinate, its index in q, or `None` for a fixed point's.
    index: [Option<usize>; MAX_LOCAL],
    /// Values of the fixed local coordinates.
    fixed: [f64; MAX_LOCAL],
}

impl Constraint {
    fn new(name: String, equation: Equation, slots: &[Slot]) -> Self {
        let mut index = [None; MAX_LOCAL];
        let mut fixed = [0.0; MAX_LOCAL];
        for (k, s) in slots.iter().enumerate() {
            match *s {
                Slot::Q(i) => index[k] = Some(i),
                Slot::Const(v) => fixed[k] = v,
            }
        }
        debug_assert_eq!(slots.len(), equation.len());
        Constraint {
            name,
            equation,
            points: Vec::new(),
            body: None,
            coordinate: None,
            index,
            fixed,
        }
    }

    /// Records the scene coordinate it defines.
    fn defining(mut self, coordinate: usize) -> Self {
        self.coordinate = Some(coordinate);
        self
    }

    /// Records which scene points its local coordinates belong to, and its body.
    fn on(mut self, points: &[usize], body: Option<usize>) -> Self {
        self.points = points.to_vec();
        self.body = body;
        self
    }

    /// Indices in q of the coordinates this constraint involves.
    pub fn coordinates(&self) -> impl Iterator<Item = usize> + '_ {
        self.index[..self.equation.len()].iter().flatten().copied()
    }

    /// For each local coordinate, its index in q (`None` for a fixed point's).
    pub fn local_index(&self) -> &[Option<usize>] {
        &self.index[..self.equation.len()]
    }

    /// The local vector u of positions.
    pub fn gather(&self, q: &[f64], u: &mut [f64; MAX_LOCAL]) {
        for k in 0..self.equation.len() {
            u[k] = match self.index[k] {
                Some(i) => q[i],
                None => self.fixed[k],
            };
        }
    }

    /// The local vector of a velocity-like quantity (zero on fixed coordinates).
    pub fn gather_rate(&self, v: &[f64], u: &mut [f64; MAX_LOCAL]) {
        for k in 0..self.equation.len() {
            u[k] = self.index[k].map_or(0.0, |i| v[i]);
        }
    }

    /// Adds the local row `local` into the global row `out` (shared coordinates add up).
    fn scatter(&self, local: &[f64], out: &mut [f64]) {
        for k in 0..self.equation.len() {
            if let Some(i) = self.index[k] {
                out[i] += local[k];
            }
        }
    }
}

#[derive(Clone, Copy)]
enum Slot {
    Q(usize),
    Const(f64),
}

/// The assembled planar multibody model.
#[derive(Debug, Clone)]
pub struct Model {
    pub scene: Scene,
    /// Coordinate names in q order.
    pub names: Vec<String>,
    pub points: Vec<PointSlot>,
    /// Index in q of the first relative coordinate.
    pub relative_offset: usize,
    pub constraints: Vec<Constraint>,
    /// Constant mass matrix (zero on relative coordinates).
    pub mass: DMatrix<f64>,
    pub forces: Vec<Force>,
    /// Indices in q of the independent coordinates the scene declares (a run in IC
    /// starts with them; a later segment's are its `forward::Start`'s).
    pub independent: Vec<usize>,
    /// Constraints kept in the dynamics: all but the redundant ones.
    pub active: Vec<usize>,
    /// Constraints that are linear combinations of earlier ones at the initial state.
    pub redundant: Vec<usize>,
    /// The scene's consistent initial state (a run's segments and substeps start
    /// from their own `forward::Start`).
    pub initial: State,
    /// The scene's sensors, located in q.
    pub sensors: Vec<crate::sensors::Sensor>,
    /// The scene's `estimation:` section, located in q.
    pub estimation: crate::sensors::EstimationSpec,
    /// The parameters an estimate identifies (`estimation: parameters:`), if any.
    pub parameters: Option<std::sync::Arc<parameters::Parameters>>,
    /// Tells this model apart from every other one, for what is kept of its
    /// evaluations between calls.
    pub identity: Identity,
}

/// A model's identity: unique in the process; a clone, which may then be changed,
/// is another model.
#[derive(Debug, PartialEq, Eq)]
pub struct Identity(u64);

impl Identity {
    fn new() -> Self {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        Identity(NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed))
    }

    pub fn get(&self) -> u64 {
        self.0
    }
}

impl Clone for Identity {
    fn clone(&self) -> Self {
        Identity::new()
    }
}

/// Positions and velocities.
#[derive(Debug, Clone, PartialEq)]
pub struct State {
    pub q: DVector<f64>,
    pub dq: DVector<f64>,
}

impl Model {
    /// A validated scene's coordinates, constraints, mass matrix, forces and
    /// independent coordinates, before its initial state is assembled: no
    /// constraint is marked active or redundant yet and the state is zero until
    /// [`Model::new`] solves for them.
    pub(crate) fn unassembled(scene: &Scene) -> Result<Model> {
        check_extent(scene)?;
        let mut points = Vec::with_capacity(scene.points.len());
        let mut n = 0;
        for p in &scene.points {
            if p.fixed {
                points.push(PointSlot::Fixed([p.x, p.y]));
            } else {
                points.push(PointSlot::Free(n));
                n += 2;
            }
        }
        let relative_offset = n;
        n += scene.coordinates.len();
        // The model's dense matrices: M, Φ_q and the KKT system of the initial state.
        let m_rows = scene.constraints.len() + 2 * scene.bodies.len();
        crate::limits::ensure_fits(
            &format!("{}: a model of {n} coordinates", scene.file),
            8.0 * ((n + m_rows) as f64).powi(2) * 4.0,
        )?;
        let names = scene::coordinate_names(scene);

        let mut model = Model {
            scene: scene.clone(),
            names,
            points,
            relative_offset,
            constraints: Vec::new(),
            mass: DMatrix::zeros(n, n),
            forces: Vec::new(),
            independent: Vec::new(),
            active: Vec::new(),
            redundant: Vec::new(),
            initial: State {
                q: DVector::zeros(n),
                dq: DVector::zeros(n),
            },
            sensors: Vec::new(),
            estimation: Default::default(),
            parameters: None,
            identity: Identity::new(),
        };
        model.build_constraints();
        model.build_mass();
        model.forces = forces::assemble(&model)?;
        model.independent = scene
            .independent
            .iter()
            .map(|name| model.index_of(name))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| Error::InvalidArgument("independent coordinate not in q".into()))?;
        model.sensors = crate::sensors::resolve(&model, &scene.sensors)?;
        model.estimation = crate::sensors::resolve_estimation(&model, &scene.estimation)?;
        model.parameters = parameters::Parameters::of(&model)?.map(std::sync::Arc::new);
        Ok(model)
    }

    /// The scene's approximate positions as q: the points where the scene places
    /// them, the relative coordinates at their given or measured values, and the
    /// scene's `initial_positions`. Not consistent with the constraints in general.
    pub(crate) fn approximate_positions(&self) -> DVector<f64> {
        let scene = &self.scene;
        let mut q = DVector::zeros(self.n());
        for (p, point) in scene.points.iter().enumerate() {
            if let PointSlot::Free(i) = self.points[p] {
                q[i] = point.x;
                q[i + 1] = point.y;
            }
        }
        for (k, c) in scene.coordinates.iter().enumerate() {
            q[self.relative_offset + k] = c
                .initial
                .unwrap_or_else(|| scene::relative_value(&scene.points, &c.kind));
        }
        for (name, value) in &scene.initial_positions {
            if let Some(i) = self.index_of(name) {
                q[i] = *value;
            }
        }
        q
    }

    /// Degrees of freedom: n minus the rank of Φ_q.
    pub fn dof(&self) -> usize {
        self.n() - self.active.len()
    }

    /// Number of coordinates n.
    pub fn n(&self) -> usize {
        self.names.len()
    }

    /// Number of constraint equations m (redundant ones included).
    pub fn m(&self) -> usize {
        self.constraints.len()
    }

    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|c| c == name)
    }

    /// Whether coordinate i of q is an angle (absolute or relative), not a point's x
    /// or y or a distance.
    pub fn is_angle(&self, i: usize) -> bool {
        i >= self.relative_offset
            && self.scene.coordinates[i - self.relative_offset]
                .kind
                .is_angle()
    }

    fn slot_point(&self, p: usize) -> [Slot; 2] {
        match self.points[p] {
            PointSlot::Free(i) => [Slot::Q(i), Slot::Q(i + 1)],
            PointSlot::Fixed(r) => [Slot::Const(r[0]), Slot::Const(r[1])],
        }
    }

    fn slots(&self, pts: &[usize], extra: Option<usize>) -> Vec<Slot> {
        let mut s: Vec<Slot> = pts.iter().flat_map(|&p| self.slot_point(p)).collect();
        s.extend(extra.map(Slot::Q));
        s
    }

    /// Rigid-body distances (a body on k points gets 2k−3 equations), then the
    /// equations of the relative coordinates, then the scene's explicit constraints.
    fn build_constraints(&mut self) {
        let scene = self.scene.clone();
        let pname = |i: usize| scene.points[i].name.clone();
        let mut out = Vec::new();
        for (bi, body) in scene.bodies.iter().enumerate() {
            let pts = &body.points;
            let distance = |a: usize, b: usize, length: f64| {
                Constraint::new(
                    format!("{}: distance({},{})", body.name, pname(a), pname(b)),
                    Equation::Distance { length },
                    &self.slots(&[a, b], None),
                )
                .on(&[a, b], Some(bi))
            };
            out.push(distance(pts[0], pts[1], body.length));
            let p = |i: usize| [scene.points[i].x, scene.points[i].y];
            for &c in &pts[2..] {
                let (a, b) = (pts[0], pts[1]);
                let (ra, rb, rc) = (p(a), p(b), p(c));
                let cross = (rb[0] - ra[0]) * (rc[1] - ra[1]) - (rb[1] - ra[1]) * (rc[0] - ra[0]);
                let dac = (rc[0] - ra[0]).hypot(rc[1] - ra[1]);
                let dbc = (rc[0] - rb[0]).hypot(rc[1] - rb[1]);
                if cross.abs() > 1e-9 * body.length * dac.max(dbc) {
                    out.push(distance(a, c, dac));
                    out.push(distance(b, c, dbc));
                } else {
                    // A point on the line of the first two: two distances would
                    // leave it free across the line to first order.
                    out.push(distance(a, c, dac));
                    out.push(
                        Constraint::new(
                            format!(
                                "{}: on line({},{}) of {}",
                                body.name,
                                pname(a),
                                pname(b),
                                pname(c)
                            ),
                            Equation::PointOnLine,
                            &self.slots(&[c, a, b], None),
                        )
                        .on(&[c, a, b], Some(bi)),
                    );
                }
            }
        }
        for (k, coord) in scene.coordinates.iter().enumerate() {
            let qi = Some(self.relative_offset + k);
            let len = |a: usize, b: usize| {
                let (pa, pb) = (&scene.points[a], &scene.points[b]);
                (pb.x - pa.x).hypot(pb.y - pa.y)
            };
            let (equation, pts): (Equation, Vec<usize>) = match coord.kind {
                RelativeKind::AbsoluteAngle { from, to } => {
                    (Equation::AbsoluteAngle, vec![from, to])
                }
                RelativeKind::RelativeAngle { a, b } => {
                    (Equation::RelativeAngle, vec![a[0], a[1], b[0], b[1]])
                }
                RelativeKind::Distance { point, along } => (
                    Equation::DistanceAlong {
                        length: self
                            .rigid_length(along[0], along[1])
                            .unwrap_or(len(along[0], along[1])),
                    },
                    vec![point, along[0], along[1]],
                ),
            };
            out.push(
                Constraint::new(
                    format!("coordinate {}", coord.name),
                    equation,
                    &self.slots(&pts, qi),
                )
                .on(&pts, None)
                .defining(k),
            );
        }
        for c in &scene.constraints {
            out.push(match c.kind {
                ConstraintKind::Distance { points, length } => Constraint::new(
                    c.name.clone(),
                    Equation::Distance { length },
                    &self.slots(&points, None),
                )
                .on(&points, None),
                ConstraintKind::FixedSlider { point, line }
                | ConstraintKind::MobileSlider { point, line } => Constraint::new(
                    c.name.clone(),
                    Equation::PointOnLine,
                    &self.slots(&[point, line[0], line[1]], None),
                )
                .on(&[point, line[0], line[1]], None),
            });
        }
        self.constraints = out;
    }

    /// The length a two-point body or explicit distance constraint keeps between a
    /// and b (it may differ from the approximate initial positions).
    fn rigid_length(&self, a: usize, b: usize) -> Option<f64> {
        let same =
            |p: &[usize]| p.len() == 2 && ((p[0] == a && p[1] == b) || (p[0] == b && p[1] == a));
        self.scene
            .bodies
            .iter()
            .find(|body| same(&body.points))
            .map(|body| body.length)
            .or_else(|| {
                self.scene.constraints.iter().find_map(|c| match c.kind {
                    ConstraintKind::Distance { points, length } if same(&points) => Some(length),
                    _ => None,
                })
            })
    }

    fn build_mass(&mut self) {
        let scene = self.scene.clone();
        for body in &scene.bodies {
            let mb = mass::body_mass_matrix(body);
            let slots = self.slots(&body.points[..2], None);
            for (a, sa) in slots.iter().enumerate() {
                for (b, sb) in slots.iter().enumerate() {
                    if let (Slot::Q(i), Slot::Q(j)) = (sa, sb) {
                        self.mass[(*i, *j)] += mb[a][b];
                    }
                }
            }
        }
        for (p, point) in scene.points.iter().enumerate() {
            if let (PointSlot::Free(i), m) = (self.points[p], point.mass) {
                self.mass[(i, i)] += m;
                self.mass[(i + 1, i + 1)] += m;
            }
        }
    }

    /// Position of point `p` at q.
    pub fn point_position(&self, q: &[f64], p: usize) -> [f64; 2] {
        match self.points[p] {
            PointSlot::Free(i) => [q[i], q[i + 1]],
            PointSlot::Fixed(r) => r,
        }
    }

    /// Velocity of point `p`.
    pub fn point_velocity(&self, dq: &[f64], p: usize) -> [f64; 2] {
        match self.points[p] {
            PointSlot::Free(i) => [dq[i], dq[i + 1]],
            PointSlot::Fixed(_) => [0.0, 0.0],
        }
    }

    /// The body turning fastest at (q, q̇): its name and |ω| (rad/s), from its first two
    /// points (ω = (r₂ − r₁) × (v₂ − v₁) / |r₂ − r₁|²). None without bodies.
    pub fn fastest_body(&self, q: &[f64], dq: &[f64]) -> Option<(String, f64)> {
        self.fastest_body_index(q, dq)
            .map(|(b, omega)| (self.scene.bodies[b].name.clone(), omega))
    }

    /// [`Model::fastest_body`] by the body's index in the scene (no name copied: a
    /// run asks at every step).
    pub fn fastest_body_index(&self, q: &[f64], dq: &[f64]) -> Option<(usize, f64)> {
        self.scene
            .bodies
            .iter()
            .enumerate()
            .filter_map(|(i, b)| {
                let (r1, r2) = (
                    self.point_position(q, b.points[0]),
                    self.point_position(q, b.points[1]),
                );
                let (v1, v2) = (
                    self.point_velocity(dq, b.points[0]),
                    self.point_velocity(dq, b.points[1]),
                );
                let e = [r2[0] - r1[0], r2[1] - r1[1]];
                let w = [v2[0] - v1[0], v2[1] - v1[1]];
                let length2 = e[0] * e[0] + e[1] * e[1];
                let omega = ((e[0] * w[1] - e[1] * w[0]) / length2).abs();
                (length2 > 0.0 && omega.is_finite()).then_some((i, omega))
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// Φ(q) into `out` (length m).
    pub fn phi_into(&self, q: &[f64], out: &mut [f64]) {
        let mut u = [0.0; MAX_LOCAL];
        for (o, c) in out.iter_mut().zip(&self.constraints) {
            c.gather(q, &mut u);
            *o = c.equation.phi(&u);
        }
    }

    /// Rows of a per-constraint local quantity scattered into a row-major m × n
    /// matrix `out` (zeroed first). `local` gets (constraint, u, w, out-row).
    fn rows_into(
        &self,
        q: &[f64],
        v: Option<&[f64]>,
        out: &mut [f64],
        local: impl Fn(&Equation, &[f64], &[f64], &mut [f64]),
    ) {
        let n = self.n();
        out[..self.m() * n].fill(0.0);
        let (mut u, mut w, mut h) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        for (row, c) in self.constraints.iter().enumerate() {
            c.gather(q, &mut u);
            if let Some(v) = v {
                c.gather_rate(v, &mut w);
            }
            local(&c.equation, &u, &w, &mut h);
            c.scatter(&h, &mut out[row * n..(row + 1) * n]);
        }
    }

    /// Φ_q(q) into a row-major m × n `out`.
    pub fn jacobian_into(&self, q: &[f64], out: &mut [f64]) {
        self.rows_into(q, None, out, |e, u, _, h| e.gradient(u, h));
    }

    /// ∂(Φ_q v)/∂q = Φ_qq v into a row-major m × n `out`. With v = q̇ this is Φ̇_q
    /// (and also ∂(Φ_q q̇)/∂q, Appendix III); with v = q̈ it is the Φ_qq q̈ term of the
    /// factor Jacobians.
    pub fn jacobian_derivative_into(&self, q: &[f64], v: &[f64], out: &mut [f64]) {
        self.rows_into(q, Some(v), out, |e, u, w, h| e.hessian_times(u, w, h));
    }

    /// ∂(Φ̇_q q̇)/∂q into a row-major m × n `out`.
    pub fn third_order_into(&self, q: &[f64], dq: &[f64], out: &mut [f64]) {
        self.rows_into(q, Some(dq), out, |e, u, w, h| e.third_order(u, w, h));
    }

    /// Φ_q q̇ into `out` (length m), each row over its constraint's own coordinates.
    pub fn constraint_rates_into(&self, q: &[f64], dq: &[f64], out: &mut [f64]) {
        let (mut u, mut w, mut g) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        for (o, c) in out.iter_mut().zip(&self.constraints) {
            c.gather(q, &mut u);
            c.gather_rate(dq, &mut w);
            c.equation.gradient(&u, &mut g);
            *o = (0..c.equation.len()).map(|k| g[k] * w[k]).sum();
        }
    }

    /// c = −Φ̇_q q̇ into `out` (length m).
    pub fn acceleration_rhs_into(&self, q: &[f64], dq: &[f64], out: &mut [f64]) {
        let (mut u, mut w, mut h) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        for (o, c) in out.iter_mut().zip(&self.constraints) {
            c.gather(q, &mut u);
            c.gather_rate(dq, &mut w);
            c.equation.hessian_times(&u, &w, &mut h);
            *o = -(0..c.equation.len()).map(|k| h[k] * w[k]).sum::<f64>();
        }
    }

    /// Row k of the row-major m × n `out` = Φᵏ_qq(q) vₖ, with vₖ row k of the
    /// row-major m × n `v`: each constraint's Hessian applied to its own vector (the
    /// derivative of the gradient Φᵏ_q in direction vₖ).
    pub fn hessian_rows_into(&self, q: &[f64], v: &[f64], out: &mut [f64]) {
        let n = self.n();
        out[..self.m() * n].fill(0.0);
        let (mut u, mut w, mut h) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        for (row, c) in self.constraints.iter().enumerate() {
            c.gather(q, &mut u);
            c.gather_rate(&v[row * n..(row + 1) * n], &mut w);
            c.equation.hessian_times(&u, &w, &mut h);
            c.scatter(&h, &mut out[row * n..(row + 1) * n]);
        }
    }

    /// Adds Σ_k λ_k ∂²Φ_k/∂q² over the active constraints (λ indexed like
    /// `active`) to the row-major n × n `out`: the derivative of Φ_qᵀλ with λ fixed.
    pub fn add_weighted_hessians(&self, q: &[f64], lambda: &[f64], out: &mut [f64]) {
        self.add_hessians_of(
            q,
            self.active.iter().copied().zip(lambda.iter().copied()),
            out,
        );
    }

    /// Adds Σ_k λ_k ∂²Φ_k/∂q² over all m constraints to the row-major n × n `out`.
    pub fn add_all_weighted_hessians(&self, q: &[f64], lambda: &[f64], out: &mut [f64]) {
        self.add_hessians_of(q, lambda.iter().copied().enumerate(), out);
    }

    fn add_hessians_of(
        &self,
        q: &[f64],
        weights: impl Iterator<Item = (usize, f64)>,
        out: &mut [f64],
    ) {
        let n = self.n();
        let (mut u, mut e, mut h) = ([0.0; MAX_LOCAL], [0.0; MAX_LOCAL], [0.0; MAX_LOCAL]);
        for (k, l) in weights {
            let c = &self.constraints[k];
            c.gather(q, &mut u);
            let len = c.equation.len();
            for a in 0..len {
                let Some(i) = c.index[a] else { continue };
                e[..len].fill(0.0);
                e[a] = 1.0;
                c.equation.hessian_times(&u, &e, &mut h);
                for b in 0..len {
                    if let Some(j) = c.index[b] {
                        out[j * n + i] += l * h[b];
                    }
                }
            }
        }
    }

    fn to_matrix(&self, rows: usize, data: &[f64]) -> DMatrix<f64> {
        DMatrix::from_row_slice(rows, self.n(), data)
    }

    /// Φ(q), all m equations.
    pub fn phi(&self, q: &DVector<f64>) -> DVector<f64> {
        let mut out = DVector::zeros(self.m());
        self.phi_into(q.as_slice(), out.as_mut_slice());
        out
    }

    /// Φ_q(q), m × n.
    pub fn jacobian(&self, q: &DVector<f64>) -> DMatrix<f64> {
        let mut out = vec![0.0; self.m() * self.n()];
        self.jacobian_into(q.as_slice(), &mut out);
        self.to_matrix(self.m(), &out)
    }

    /// ∂(Φ_q v)/∂q = Φ_qq v, m × n (see [`Model::jacobian_derivative_into`]).
    pub fn jacobian_derivative(&self, q: &DVector<f64>, v: &DVector<f64>) -> DMatrix<f64> {
        let mut out = vec![0.0; self.m() * self.n()];
        self.jacobian_derivative_into(q.as_slice(), v.as_slice(), &mut out);
        self.to_matrix(self.m(), &out)
    }

    /// Φ̇_q = d(Φ_q)/dt at (q, q̇).
    pub fn jacobian_dot(&self, q: &DVector<f64>, dq: &DVector<f64>) -> DMatrix<f64> {
        self.jacobian_derivative(q, dq)
    }

    /// ∂(Φ̇_q q̇)/∂q, m × n: the second-order term of the acceleration equations.
    pub fn jacobian_dot_times_rate_derivative(
        &self,
        q: &DVector<f64>,
        dq: &DVector<f64>,
    ) -> DMatrix<f64> {
        let mut out = vec![0.0; self.m() * self.n()];
        self.third_order_into(q.as_slice(), dq.as_slice(), &mut out);
        self.to_matrix(self.m(), &out)
    }

    /// c = −Φ̇_q q̇, the right-hand side of the acceleration equations Φ_q q̈ = c.
    pub fn acceleration_rhs(&self, q: &DVector<f64>, dq: &DVector<f64>) -> DVector<f64> {
        let mut out = DVector::zeros(self.m());
        self.acceleration_rhs_into(q.as_slice(), dq.as_slice(), out.as_mut_slice());
        out
    }

    /// Generalized forces Q(q, q̇, t) of the scene's effects.
    pub fn generalized_forces(
        &self,
        q: &DVector<f64>,
        dq: &DVector<f64>,
        t: f64,
    ) -> Result<DVector<f64>> {
        let mut out = DVector::zeros(self.n());
        for (i, f) in self.forces.iter().enumerate() {
            f.add_to(self, q.as_slice(), dq.as_slice(), t, out.as_mut_slice())
                .map_err(|e| self.effect_error(i, e))?;
        }
        Ok(out)
    }

    /// Effect i's evaluation error, named as `mbfg check` names the effect (a value
    /// that is not finite says where it comes from).
    pub fn effect_error(&self, i: usize, e: Error) -> Error {
        let effect = self.scene.effects[i].describe(&self.scene);
        match e {
            Error::InvalidArgument(m) => Error::InvalidArgument(format!("effect {effect}: {m}")),
            other => other,
        }
    }

    /// The first effect whose force at (q, q̇, t) cannot be evaluated or is not finite,
    /// named as `mbfg check` names it, with the reason: why a step's cost went
    /// non-finite.
    pub fn effect_fault(&self, q: &[f64], dq: &[f64], t: f64) -> Option<String> {
        let n = self.n();
        let mut out = vec![0.0; n];
        let (mut kq, mut kv) = (vec![0.0; n * n], vec![0.0; n * n]);
        for (i, f) in self.forces.iter().enumerate() {
            out.fill(0.0);
            let effect = self.scene.effects[i].describe(&self.scene);
            match f.add_to(self, q, dq, t, &mut out) {
                Err(Error::InvalidArgument(m)) => return Some(format!("effect {effect}: {m}")),
                Err(e) => return Some(format!("effect {effect}: {e}")),
                Ok(()) if !out.iter().all(|v| v.is_finite()) => {
                    return Some(format!("effect {effect} is not finite at t = {t} s"))
                }
                Ok(()) => {}
            }
            // A finite value whose derivative is not (a square root, a power below 1 or
            // an atan2 at 0) leaves the solver without a Newton step.
            kq.fill(0.0);
            kv.fill(0.0);
            let derivative = f.add_jacobians(self, (q, dq, t), &mut kq, &mut kv);
            if derivative.is_err() || !kq.iter().chain(&kv).all(|v| v.is_finite()) {
                return Some(format!(
                    "effect {effect}: its derivative with respect to the state is not finite at t = {t} s (a square root, a power below 1 or an atan2 at 0?)"
                ));
            }
        }
        None
    }

    /// ∂Q/∂q and ∂Q/∂q̇ (n × n each) at (q, q̇, t), in closed form (by forward
    /// differences for an external load).
    pub fn force_jacobians(
        &self,
        q: &DVector<f64>,
        dq: &DVector<f64>,
        t: f64,
    ) -> Result<(DMatrix<f64>, DMatrix<f64>)> {
        let n = self.n();
        let (mut kq, mut kv) = (vec![0.0; n * n], vec![0.0; n * n]);
        for (i, f) in self.forces.iter().enumerate() {
            f.add_jacobians(self, (q.as_slice(), dq.as_slice(), t), &mut kq, &mut kv)
                .map_err(|e| self.effect_error(i, e))?;
        }
        Ok((self.to_matrix(n, &kq), self.to_matrix(n, &kv)))
    }

    /// Adds generalized forces computed outside the scene (a Python controller) as the
    /// effect `name`, after the scene's own. The name must not be taken.
    pub fn add_external_load(
        &mut self,
        name: &str,
        load: std::sync::Arc<dyn forces::ExternalLoad>,
    ) -> Result<()> {
        if name.trim().is_empty() {
            return Err(Error::InvalidArgument("an effect needs a name".into()));
        }
        if self.scene.effects.iter().any(|e| e.name() == Some(name)) {
            return Err(Error::InvalidArgument(format!(
                "the scene already has an effect named '{name}'"
            )));
        }
        self.scene.effects.push(Effect::External {
            name: name.to_string(),
        });
        self.forces.push(Force::external(name, load));
        Ok(())
    }

    /// The nonzeros of M as (row, column, value), row by row: what a large
    /// mechanism's per-step work reads instead of the dense n × n matrix.
    pub fn mass_entries(&self) -> Vec<(usize, usize, f64)> {
        let n = self.n();
        (0..n)
            .flat_map(|i| (0..n).map(move |j| (i, j)))
            .filter_map(|(i, j)| {
                let m = self.mass[(i, j)];
                (m != 0.0).then_some((i, j, m))
            })
            .collect()
    }

    /// Kinetic energy ½ q̇ᵀ M q̇.
    pub fn kinetic_energy(&self, dq: &DVector<f64>) -> f64 {
        0.5 * dq.dot(&(&self.mass * dq))
    }

    /// Potential energy of gravity and springs (zero when the scene has none).
    pub fn potential_energy(&self, q: &DVector<f64>) -> f64 {
        self.forces
            .iter()
            .map(|f| f.potential(self, q.as_slice()))
            .fold(0.0, |a, b| a + b)
    }
}

/// Refuses points placed beyond [`crate::limits::MAX_COORDINATE`] or masses that are
/// not finite: the constraint equations square lengths and would lose every digit.
fn check_extent(scene: &Scene) -> Result<()> {
    let limit = crate::limits::MAX_COORDINATE;
    let refuse = |i: usize, key: &str, message: String| {
        Err(Error::Scene(crate::error::SceneError {
            file: scene.file.clone(),
            line: None,
            key: format!("points[{i}].{key}"),
            message,
        }))
    };
    for (i, p) in scene.points.iter().enumerate() {
        for (axis, v) in [("x", p.x), ("y", p.y)] {
            if !(v.abs() <= limit) {
                return refuse(
                    i,
                    axis,
                    format!(
                        "point '{}' at {axis} = {v:e} m is beyond the ±{limit:e} m a scene may span",
                        p.name
                    ),
                );
            }
        }
        if !p.mass.is_finite() {
            return refuse(i, "mass", format!("mass {} is not finite", p.mass));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn fourbar() -> Model {
        let text = "
points:
  - {name: A, x: 0, y: 0, fixed: true}
  - {name: P1, x: 1, y: 0}
  - {name: P2, x: 1, y: 2}
  - {name: B, x: 4, y: 0, fixed: true}
bodies:
  - {name: crank, points: [A, P1], mass: 1}
  - {name: coupler, points: [P1, P2], mass: 2}
  - {name: rocker, points: [P2, B], mass: 4}
effects:
  - {type: gravity, vector: [0, -9.81]}
";
        Model::new(&Scene::from_str(text, Path::new("fourbar.yaml")).unwrap()).unwrap()
    }

    #[test]
    fn fourbar_layout() {
        let m = fourbar();
        assert_eq!(m.names, ["P1.x", "P1.y", "P2.x", "P2.y"]);
        assert_eq!(m.m(), 3);
        let q = DVector::from_vec(vec![1.0, 0.0, 1.0, 2.0]);
        assert!(m.phi(&q).amax() < 1e-12);
    }
}
