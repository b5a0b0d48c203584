//! The reduced camera system `S δc = g` of the Schur complement: a symmetric block-sparse
//! matrix of 6x6 blocks (one block row/column per free keyframe), stored as its upper block
//! triangle and solved with faer, either densely (LLᵀ of the full `6n x 6n` matrix) or with a
//! sparse supernodal/simplicial LLᵀ after an AMD ordering (symbolic analysis once per
//! problem, numeric factorisation per LM step).

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::SymbolicSparseColMatRef;
use faer::{Mat, Par, Side};
use nalgebra::{Matrix6, Vector6};

use crate::CoreError;

/// Which factorisation solves the reduced camera system.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearSolverKind {
    /// Dense LLᵀ up to [`super::BaParams::dense_max_keyframes`] free keyframes, sparse above.
    Auto,
    /// Dense LLᵀ (faer) of the full reduced matrix.
    Dense,
    /// Sparse LLᵀ (faer, AMD ordering, symbolic analysis reused across iterations).
    Sparse,
}

/// Block-sparse symmetric reduced camera system and its factorisation workspace.
pub(super) struct ReducedSystem {
    /// Number of block rows/columns (free keyframes).
    n: usize,
    /// Block column `j` holds the block rows `blk_row[blk_start[j]..blk_start[j + 1]]`,
    /// ascending, all `<= j`, the last one being `j` (the diagonal block).
    blk_start: Vec<usize>,
    blk_row: Vec<u32>,
    /// Upper-triangle blocks `S[i][j]`, `i <= j`, in the order of `blk_row`.
    pub blocks: Vec<Matrix6<f64>>,
    /// Right-hand side per block row; overwritten with the solution by [`Self::solve`].
    pub rhs: Vec<Vector6<f64>>,
    sparse: bool,
    dense: Mat<f64>,
    rhs_mat: Mat<f64>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    values: Vec<f64>,
    symbolic: Option<SymbolicCholesky<usize>>,
    l_values: Vec<f64>,
    mem: Option<MemBuffer>,
    mem_bytes: usize,
}

impl Default for ReducedSystem {
    fn default() -> Self {
        Self {
            n: 0,
            blk_start: Vec::new(),
            blk_row: Vec::new(),
            blocks: Vec::new(),
            rhs: Vec::new(),
            sparse: false,
            dense: Mat::new(),
            rhs_mat: Mat::new(),
            col_ptr: Vec::new(),
            row_idx: Vec::new(),
            values: Vec::new(),
            symbolic: None,
            l_values: Vec::new(),
            mem: None,
            mem_bytes: 0,
        }
    }
}

impl std::fmt::Debug for ReducedSystem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ReducedSystem")
            .field("n", &self.n)
            .field("blocks", &self.blocks.len())
            .field("sparse", &self.sparse)
            .field("nnz", &self.values.len())
            .field("factor_nnz", &self.l_values.len())
            .field("scratch_bytes", &self.mem_bytes)
            .finish()
    }
}

impl ReducedSystem {
    /// Builds the block pattern from the (unordered, possibly repeated) upper block pairs
    /// `(i, j)` with `i <= j` found in `pairs` (which is sorted and deduplicated here; the
    /// diagonal blocks are added), and prepares the chosen factorisation. Allocates; called
    /// once per problem.
    pub fn setup(
        &mut self,
        n: usize,
        pairs: &mut Vec<(u32, u32)>,
        sparse: bool,
    ) -> Result<(), CoreError> {
        self.n = n;
        self.sparse = sparse;
        pairs.extend((0..n as u32).map(|i| (i, i)));
        // Column-major order: by column j, then row i.
        pairs.sort_unstable_by_key(|&(i, j)| (j, i));
        pairs.dedup();
        self.blk_start.clear();
        self.blk_row.clear();
        self.blk_start.push(0);
        let mut col = 0u32;
        for &(i, j) in pairs.iter() {
            while col < j {
                self.blk_start.push(self.blk_row.len());
                col += 1;
            }
            self.blk_row.push(i);
        }
        while self.blk_start.len() < n + 1 {
            self.blk_start.push(self.blk_row.len());
        }
        self.blocks.clear();
        self.blocks.resize(self.blk_row.len(), Matrix6::zeros());
        self.rhs.clear();
        self.rhs.resize(n, Vector6::zeros());
        let dim = 6 * n;
        self.rhs_mat.resize_with(dim, 1, |_, _| 0.0);
        let par = Par::Seq;
        let req = if sparse {
            self.dense = Mat::new();
            self.setup_sparse()?
        } else {
            self.symbolic = None;
            self.dense.resize_with(dim, dim, |_, _| 0.0);
            // Blocks outside the pattern are never written: clear what a previous problem left.
            self.dense.as_mut().fill(0.0);
            llt::factor::cholesky_in_place_scratch::<f64>(dim, par, Default::default())
                .or(llt::solve::solve_in_place_scratch::<f64>(dim, 1, par))
        };
        let bytes = req.size_bytes().saturating_add(req.align_bytes());
        if self.mem.is_none() || bytes > self.mem_bytes {
            self.mem = Some(
                MemBuffer::try_new(req)
                    .map_err(|_| CoreError::Degenerate("ba: out of memory".into()))?,
            );
            self.mem_bytes = bytes;
        }
        Ok(())
    }

    /// Scalar CSC pattern of the upper triangle, symbolic analysis; returns the scratch size.
    fn setup_sparse(&mut self) -> Result<StackReq, CoreError> {
        let n = self.n;
        self.col_ptr.clear();
        self.row_idx.clear();
        self.col_ptr.push(0);
        for j in 0..n {
            let rows = &self.blk_row[self.blk_start[j]..self.blk_start[j + 1]];
            for b in 0..6 {
                for &i in rows {
                    let i = i as usize;
                    let last = if i == j { b + 1 } else { 6 };
                    self.row_idx.extend((0..last).map(|a| 6 * i + a));
                }
                self.col_ptr.push(self.row_idx.len());
            }
        }
        self.values.clear();
        self.values.resize(self.row_idx.len(), 0.0);
        let dim = 6 * n;
        let pattern =
            SymbolicSparseColMatRef::new_checked(dim, dim, &self.col_ptr, None, &self.row_idx);
        let symbolic = factorize_symbolic_cholesky(
            pattern,
            Side::Upper,
            SymmetricOrdering::Amd,
            CholeskySymbolicParams::default(),
        )
        .map_err(|e| {
            CoreError::Degenerate(format!("ba: sparse symbolic analysis failed: {e:?}"))
        })?;
        self.l_values.clear();
        self.l_values.resize(symbolic.len_val(), 0.0);
        let par = Par::Seq;
        let req = symbolic
            .factorize_numeric_llt_scratch::<f64>(par, Default::default())
            .or(symbolic.solve_in_place_scratch::<f64>(1, par));
        self.symbolic = Some(symbolic);
        Ok(req)
    }

    /// Number of block rows.
    #[inline]
    pub fn n(&self) -> usize {
        self.n
    }

    /// Zeroes all blocks and the right-hand side.
    pub fn clear(&mut self) {
        self.blocks.iter_mut().for_each(|b| *b = Matrix6::zeros());
        self.rhs.iter_mut().for_each(|r| *r = Vector6::zeros());
    }

    /// Index into [`Self::blocks`] of block `(i, j)`, `i <= j`, if it is in the pattern.
    #[inline]
    pub fn block_index(&self, i: u32, j: u32) -> Option<usize> {
        let (s, e) = (self.blk_start[j as usize], self.blk_start[j as usize + 1]);
        self.blk_row[s..e].binary_search(&i).ok().map(|k| s + k)
    }

    /// Index of the diagonal block `(j, j)` (always present: last of its column).
    #[inline]
    pub fn diag_index(&self, j: usize) -> usize {
        self.blk_start[j + 1] - 1
    }

    /// Factorises `S` and overwrites [`Self::rhs`] with `S⁻¹ rhs`. Errors (without panicking)
    /// when `S` is not numerically positive definite or the workspace is missing.
    pub fn solve(&mut self) -> Result<(), CoreError> {
        let n = self.n;
        if n == 0 {
            return Ok(());
        }
        for (j, r) in self.rhs.iter().enumerate() {
            for a in 0..6 {
                self.rhs_mat[(6 * j + a, 0)] = r[a];
            }
        }
        let Some(mem) = self.mem.as_mut() else {
            return Err(CoreError::Degenerate("ba: no workspace".into()));
        };
        let stack = MemStack::new(mem);
        let par = Par::Seq;
        if self.sparse {
            let mut k = 0;
            for j in 0..n {
                let rows = &self.blk_row[self.blk_start[j]..self.blk_start[j + 1]];
                let blocks = &self.blocks[self.blk_start[j]..self.blk_start[j + 1]];
                for b in 0..6 {
                    for (&i, blk) in rows.iter().zip(blocks) {
                        let last = if i as usize == j { b + 1 } else { 6 };
                        for a in 0..last {
                            self.values[k] = blk[(a, b)];
                            k += 1;
                        }
                    }
                }
            }
            let Some(symbolic) = self.symbolic.as_ref() else {
                return Err(CoreError::Degenerate(
                    "ba: no symbolic factorisation".into(),
                ));
            };
            crate::optim::sparse_llt::factor_solve_upper(
                symbolic,
                6 * n,
                &self.col_ptr,
                &self.row_idx,
                &self.values,
                &mut self.l_values,
                self.rhs_mat.as_mut(),
                stack,
            )
            .map_err(|()| {
                CoreError::Degenerate("ba: reduced system not positive definite".into())
            })?;
        } else {
            for j in 0..n {
                for k in self.blk_start[j]..self.blk_start[j + 1] {
                    let i = self.blk_row[k] as usize;
                    let blk = &self.blocks[k];
                    for b in 0..6 {
                        for a in 0..6 {
                            // Both triangles (the factorisation reads the lower one).
                            self.dense[(6 * i + a, 6 * j + b)] = blk[(a, b)];
                            self.dense[(6 * j + b, 6 * i + a)] = blk[(a, b)];
                        }
                    }
                }
            }
            llt::factor::cholesky_in_place(
                self.dense.as_mut(),
                Default::default(),
                par,
                stack,
                Default::default(),
            )
            .map_err(|_| {
                CoreError::Degenerate("ba: reduced system not positive definite".into())
            })?;
            llt::solve::solve_in_place(self.dense.as_ref(), self.rhs_mat.as_mut(), par, stack);
        }
        for (j, r) in self.rhs.iter_mut().enumerate() {
            for a in 0..6 {
                r[a] = self.rhs_mat[(6 * j + a, 0)];
            }
        }
        if self.rhs.iter().all(|r| r.iter().all(|v| v.is_finite())) {
            Ok(())
        } else {
            Err(CoreError::Degenerate(
                "ba: non-finite reduced solution".into(),
            ))
        }
    }
}
