//! The solver's memory: one const-generic value at the edge of the program ([`SolverWorkspace`],
//! whose `size_of` is the budget), lent to the solver as plain slices ([`SolverBuffers`]), so
//! the solver itself compiles once for every capacity.

use crate::geom::Se2;

/// A 3x3 block, row major.
pub type Block = [f64; 9];

/// The rows of `m`, one after another: a 3x3 matrix in the layout of a [`Block`].
#[inline(always)]
pub(crate) fn rows_of(m: &nalgebra::Matrix3<f64>) -> Block {
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}
/// A 3-vector.
pub type Vec3 = [f64; 3];

/// What the last structural analysis was computed for; the ordering and the symbolic factor
/// are reused while the graph's structure (nodes, fixed flags, edge endpoints) is unchanged.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AnalysisKey {
    pub(crate) nodes: usize,
    pub(crate) edges: usize,
    pub(crate) fingerprint: u64,
    pub(crate) valid: bool,
    pub(crate) vars: usize,
    /// Off-diagonal blocks of the factor.
    pub(crate) nnz: usize,
    /// The factor's storage holds the Cholesky factor of the last assembled system (of this
    /// analysis, with the edges' current active flags).
    pub(crate) factored: bool,
}

/// Workspace for graphs of up to `NODES` nodes and `EDGES` edges whose Cholesky factor has at
/// most `FACTOR` off-diagonal 3x3 blocks (fill included).
///
/// A fill-reducing ordering keeps the factor of a planar pose graph small: measured on the
/// public datasets it is 2 to 13 blocks per node (see the README); size `FACTOR` accordingly.
#[derive(Debug)]
pub struct SolverWorkspace<const NODES: usize, const EDGES: usize, const FACTOR: usize> {
    key: AnalysisKey,
    node_var: [u32; NODES],
    var_node: [u32; NODES],
    col_end: [u32; NODES],
    diag: [Block; NODES],
    work: [Block; NODES],
    rhs: [Vec3; NODES],
    step: [Vec3; NODES],
    saved: [Se2; NODES],
    scratch_a: [u32; NODES],
    scratch_b: [u32; NODES],
    scratch_c: [u32; NODES],
    scratch_d: [u32; NODES],
    scratch_e: [u32; NODES],
    scratch_f: [u32; NODES],
    edge_slot: [u32; EDGES],
    edge_trig: [[f64; 2]; EDGES],
    edge_flags: [u8; EDGES],
    rows: [u32; FACTOR],
    values: [Block; FACTOR],
    adj_node: [[u32; 2]; FACTOR],
    adj_next: [[u32; 2]; FACTOR],
}

impl<const NODES: usize, const EDGES: usize, const FACTOR: usize>
    SolverWorkspace<NODES, EDGES, FACTOR>
{
    /// A zeroed workspace, usable as a `static` initialiser.
    pub const fn new() -> Self {
        SolverWorkspace {
            key: AnalysisKey {
                nodes: 0,
                edges: 0,
                fingerprint: 0,
                valid: false,
                vars: 0,
                nnz: 0,
                factored: false,
            },
            node_var: [0; NODES],
            var_node: [0; NODES],
            col_end: [0; NODES],
            diag: [[0.0; 9]; NODES],
            work: [[0.0; 9]; NODES],
            rhs: [[0.0; 3]; NODES],
            step: [[0.0; 3]; NODES],
            saved: [Se2::IDENTITY; NODES],
            scratch_a: [0; NODES],
            scratch_b: [0; NODES],
            scratch_c: [0; NODES],
            scratch_d: [0; NODES],
            scratch_e: [0; NODES],
            scratch_f: [0; NODES],
            edge_slot: [0; EDGES],
            edge_trig: [[0.0; 2]; EDGES],
            edge_flags: [0; EDGES],
            rows: [0; FACTOR],
            values: [[0.0; 9]; FACTOR],
            adj_node: [[0; 2]; FACTOR],
            adj_next: [[0; 2]; FACTOR],
        }
    }

    /// The workspace as slices, for [`crate::solver::solve`].
    pub fn buffers(&mut self) -> SolverBuffers<'_> {
        SolverBuffers {
            key: &mut self.key,
            node_var: &mut self.node_var,
            var_node: &mut self.var_node,
            col_end: &mut self.col_end,
            diag: &mut self.diag,
            work: &mut self.work,
            rhs: &mut self.rhs,
            step: &mut self.step,
            saved: &mut self.saved,
            scratch: [
                &mut self.scratch_a,
                &mut self.scratch_b,
                &mut self.scratch_c,
                &mut self.scratch_d,
                &mut self.scratch_e,
                &mut self.scratch_f,
            ],
            edge_slot: &mut self.edge_slot,
            edge_trig: &mut self.edge_trig,
            edge_flags: &mut self.edge_flags,
            rows: &mut self.rows,
            values: &mut self.values,
            adj_node: self.adj_node.as_flattened_mut(),
            adj_next: self.adj_next.as_flattened_mut(),
        }
    }
}

impl<const NODES: usize, const EDGES: usize, const FACTOR: usize> Default
    for SolverWorkspace<NODES, EDGES, FACTOR>
{
    fn default() -> Self {
        Self::new()
    }
}

/// The solver's memory as borrowed slices; see [`SolverWorkspace::buffers`].
///
/// A host with heap memory may build one from vectors instead: node-sized slices need at least
/// the graph's node count, edge-sized ones its edge count, `rows` and `values` the factor's
/// block count and `adj_node`/`adj_next` twice that. [`crate::solver::solve`] checks the
/// lengths and reports [`crate::solver::SolveError::Capacity`]; the contents need no
/// initialisation (start `key` at its default).
#[derive(Debug)]
pub struct SolverBuffers<'a> {
    /// What the cached analysis was computed for.
    pub key: &'a mut AnalysisKey,
    /// node index -> variable position in the elimination order (`u32::MAX` when fixed).
    pub node_var: &'a mut [u32],
    /// variable position -> node index.
    pub var_node: &'a mut [u32],
    /// End (exclusive) of each factor column in `rows`/`values`.
    pub col_end: &'a mut [u32],
    /// Diagonal blocks: the system's, then the inverse of the factor's diagonal block.
    pub diag: &'a mut [Block],
    /// Dense column accumulator of the numeric factorization.
    pub work: &'a mut [Block],
    /// Right-hand side (gradient), then solution.
    pub rhs: &'a mut [Vec3],
    /// Step of the last iteration, per variable.
    pub step: &'a mut [Vec3],
    /// Poses saved before a trial step (Levenberg-Marquardt).
    pub saved: &'a mut [Se2],
    /// Integer scratch for the ordering and the factorization.
    pub scratch: [&'a mut [u32]; 6],
    /// Per edge: index of its off-diagonal block in `values` (top bit: stored transposed).
    pub edge_slot: &'a mut [u32],
    /// Per edge: cosine and sine of its measured angle.
    pub edge_trig: &'a mut [[f64; 2]],
    /// Per edge: 1 when it takes part in the linear system (see [`crate::solver`]).
    pub edge_flags: &'a mut [u8],
    /// Row (variable position) of each off-diagonal factor block.
    pub rows: &'a mut [u32],
    /// Off-diagonal blocks: the system's, then the factor's.
    pub values: &'a mut [Block],
    /// Elimination-graph adjacency (ordering only): neighbour of each list entry.
    pub adj_node: &'a mut [u32],
    /// Elimination-graph adjacency (ordering only): next entry of each list.
    pub adj_next: &'a mut [u32],
}

impl SolverBuffers<'_> {
    /// Most nodes a graph may have.
    pub fn node_capacity(&self) -> usize {
        self.node_var.len()
    }

    /// Most edges a graph may have.
    pub fn edge_capacity(&self) -> usize {
        self.edge_slot.len()
    }

    /// Most off-diagonal blocks the factor may have.
    pub fn factor_capacity(&self) -> usize {
        self.rows.len()
    }

    /// Forgets the cached ordering, so the next solve analyses the structure again.
    pub fn invalidate(&mut self) {
        self.key.valid = false;
    }
}
