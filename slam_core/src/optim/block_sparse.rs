//! The one symmetric block-sparse linear system of the crate: bundle adjustment's reduced
//! camera system (6x6 pose blocks after the Schur complement on the points), the pose-graph
//! optimiser's normal equations (6x6 SE(3) or 7x7 Sim(3) blocks, or a subset of their
//! coordinates) and the chordal initialisation (3x3 and 1x1 blocks) all assemble
//! `H x = rhs` here, block by block, and solve it with faer.
//!
//! **Layout.** Block row/column `i` has its own size (`sizes[i]` unknowns), so states of
//! different dimensions can share one system (a visual-inertial problem: a 6-dof pose block
//! and a 9-dof velocity-and-biases block per keyframe, or one 15-dof block). Only the upper
//! block triangle is stored: block column `j` holds block rows `i <= j`, ascending, the last
//! one being the diagonal block; each block is `sizes[i] x sizes[j]` values, column-major.
//! The pattern is fixed once per problem ([`BlockSparseSystem::setup`]); assembling
//! ([`BlockSparseSystem::add_block`], [`BlockSparseSystem::add_to_block`],
//! [`BlockSparseSystem::add_rhs`], fixed-size views) and solving allocate nothing.
//!
//! **Factorisations** ([`Factorization`]): a dense LLᵀ of the full matrix (few unknowns), or
//! a sparse LLᵀ with the symbolic analysis made once per problem and the numeric
//! factorisation per solve, ordered either by AMD on the scalar pattern (faer chooses
//! simplicial or supernodal) or by AMD on the block graph expanded block-wise (supernodal
//! forced: measured 2-3x faster on the large pose graphs).

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt;
use faer::perm::PermRef;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, Mat, Par, Side};
use nalgebra::{SMatrix, SMatrixViewMut, SVector};

use crate::CoreError;

/// How [`BlockSparseSystem::solve`] factorises the matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Factorization {
    /// Dense LLᵀ of the full symmetric matrix.
    Dense,
    /// Sparse LLᵀ after an AMD ordering of the scalar pattern (faer's automatic choice of
    /// simplicial or supernodal factorisation).
    SparseScalarAmd,
    /// Sparse supernodal LLᵀ after an AMD ordering of the block graph, expanded block-wise
    /// (cheaper ordering, contiguous blocks).
    SparseBlockAmd,
}

/// A symmetric block-sparse system `H x = rhs` (with `nrhs` right-hand sides) and its
/// factorisation workspace; see the module docs.
pub struct BlockSparseSystem {
    /// Prefix of error messages (`"ba"`, `"pgo"`).
    name: &'static str,
    n: usize,
    nrhs: usize,
    /// Scalar offset of each block row (`n + 1` entries, the last = dimension).
    offset: Vec<usize>,
    /// Block column `j` holds the block rows `blk_row[blk_start[j]..blk_start[j + 1]]`.
    blk_start: Vec<usize>,
    blk_row: Vec<u32>,
    /// Column of each stored block and the offset of its values in `blocks`.
    blk_col: Vec<u32>,
    blk_off: Vec<usize>,
    blocks: Vec<f64>,
    /// `dim x nrhs`, column-major.
    rhs: Vec<f64>,
    x: Vec<f64>,
    factorization: Factorization,
    dense: Mat<f64>,
    rhs_mat: Mat<f64>,
    /// Scalar CSC pattern of the upper triangle (sparse factorisations).
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// For each scalar entry of that pattern: its index into `blocks`.
    src: Vec<usize>,
    /// Positions in `values` of the scalar diagonal.
    diag_pos: Vec<usize>,
    values: Vec<f64>,
    symbolic: Option<SymbolicCholesky<usize>>,
    l_values: Vec<f64>,
    mem: Option<MemBuffer>,
    mem_bytes: usize,
}

impl BlockSparseSystem {
    /// An empty system whose errors start with `name`.
    pub fn new(name: &'static str) -> Self {
        Self {
            name,
            n: 0,
            nrhs: 0,
            offset: vec![0],
            blk_start: Vec::new(),
            blk_row: Vec::new(),
            blk_col: Vec::new(),
            blk_off: Vec::new(),
            blocks: Vec::new(),
            rhs: Vec::new(),
            x: Vec::new(),
            factorization: Factorization::Dense,
            dense: Mat::new(),
            rhs_mat: Mat::new(),
            col_ptr: Vec::new(),
            row_idx: Vec::new(),
            src: Vec::new(),
            diag_pos: Vec::new(),
            values: Vec::new(),
            symbolic: None,
            l_values: Vec::new(),
            mem: None,
            mem_bytes: 0,
        }
    }

    fn err(&self, what: &str) -> CoreError {
        CoreError::Degenerate(format!("{}: {what}", self.name))
    }

    /// [`Self::setup`] with `n` blocks of `block_size` unknowns each.
    pub fn setup_uniform(
        &mut self,
        n: usize,
        block_size: usize,
        nrhs: usize,
        pairs: &mut Vec<(u32, u32)>,
        factorization: Factorization,
    ) -> Result<(), CoreError> {
        self.offset.clear();
        self.offset.extend((0..=n).map(|i| i * block_size));
        self.setup_pattern(nrhs, pairs, factorization)
    }

    /// Block sizes, block pattern and factorisation. The off-diagonal block pairs `(i, j)`
    /// of `pairs` may come in any order and repeat (`pairs` is normalised to `i <= j`,
    /// completed with the diagonal, sorted and deduplicated in place: reusable scratch).
    /// Prepares the chosen factorisation (symbolic analysis for the sparse ones). Allocates
    /// only when the problem outgrows earlier ones (the sparse symbolic analysis always).
    pub fn setup(
        &mut self,
        sizes: &[usize],
        nrhs: usize,
        pairs: &mut Vec<(u32, u32)>,
        factorization: Factorization,
    ) -> Result<(), CoreError> {
        self.offset.clear();
        self.offset.push(0);
        let mut o = 0;
        for &s in sizes {
            o += s;
            self.offset.push(o);
        }
        self.setup_pattern(nrhs, pairs, factorization)
    }

    fn setup_pattern(
        &mut self,
        nrhs: usize,
        pairs: &mut Vec<(u32, u32)>,
        factorization: Factorization,
    ) -> Result<(), CoreError> {
        let n = self.offset.len() - 1;
        if pairs.iter().any(|&(i, j)| i.max(j) as usize >= n) {
            return Err(CoreError::InvalidArgument(format!(
                "{}: block pair out of range",
                self.name
            )));
        }
        self.n = n;
        self.nrhs = nrhs;
        self.factorization = factorization;
        for p in pairs.iter_mut() {
            *p = (p.0.min(p.1), p.0.max(p.1));
        }
        pairs.extend((0..n as u32).map(|i| (i, i)));
        // Column-major order: by column j, then row i.
        pairs.sort_unstable_by_key(|&(i, j)| (j, i));
        pairs.dedup();
        self.blk_start.clear();
        self.blk_row.clear();
        self.blk_col.clear();
        self.blk_off.clear();
        self.blk_start.push(0);
        let mut col = 0u32;
        let mut off = 0;
        for &(i, j) in pairs.iter() {
            while col < j {
                self.blk_start.push(self.blk_row.len());
                col += 1;
            }
            self.blk_row.push(i);
            self.blk_col.push(j);
            self.blk_off.push(off);
            off += self.size(i as usize) * self.size(j as usize);
        }
        while self.blk_start.len() < n + 1 {
            self.blk_start.push(self.blk_row.len());
        }
        self.blocks.clear();
        self.blocks.resize(off, 0.0);
        let dim = self.dim();
        self.rhs.clear();
        self.rhs.resize(dim * nrhs, 0.0);
        self.x.clear();
        self.x.resize(dim * nrhs, 0.0);
        self.rhs_mat.resize_with(dim, nrhs, |_, _| 0.0);
        let par = Par::Seq;
        let req = match factorization {
            Factorization::Dense => {
                self.symbolic = None;
                self.dense.resize_with(dim, dim, |_, _| 0.0);
                llt::factor::cholesky_in_place_scratch::<f64>(dim, par, Default::default())
                    .or(llt::solve::solve_in_place_scratch::<f64>(dim, nrhs, par))
            }
            Factorization::SparseScalarAmd | Factorization::SparseBlockAmd => {
                self.dense = Mat::new();
                self.setup_sparse()?
            }
        };
        let bytes = req.size_bytes().saturating_add(req.align_bytes());
        if self.mem.is_none() || bytes > self.mem_bytes {
            self.mem = Some(MemBuffer::try_new(req).map_err(|_| self.err("out of memory"))?);
            self.mem_bytes = bytes;
        }
        Ok(())
    }

    /// Scalar CSC pattern of the upper triangle and symbolic analysis; returns the scratch
    /// size of the numeric factorisation and solve.
    fn setup_sparse(&mut self) -> Result<StackReq, CoreError> {
        self.col_ptr.clear();
        self.row_idx.clear();
        self.src.clear();
        self.diag_pos.clear();
        self.col_ptr.push(0);
        for j in 0..self.n {
            for b in 0..self.size(j) {
                for k in self.blk_start[j]..self.blk_start[j + 1] {
                    let i = self.blk_row[k] as usize;
                    let rows = self.size(i);
                    let last = if i == j { b + 1 } else { rows };
                    for a in 0..last {
                        if i == j && a == b {
                            self.diag_pos.push(self.row_idx.len());
                        }
                        self.row_idx.push(self.offset[i] + a);
                        self.src.push(self.blk_off[k] + a + rows * b);
                    }
                }
                self.col_ptr.push(self.row_idx.len());
            }
        }
        self.values.clear();
        self.values.resize(self.row_idx.len(), 0.0);
        let dim = self.dim();
        let pattern =
            SymbolicSparseColMatRef::new_checked(dim, dim, &self.col_ptr, None, &self.row_idx);
        let symbolic = match self.factorization {
            Factorization::SparseBlockAmd => {
                let (perm, perm_inv) = self.block_amd_permutation()?;
                factorize_symbolic_cholesky(
                    pattern,
                    Side::Upper,
                    SymmetricOrdering::Custom(PermRef::new_checked(&perm, &perm_inv, dim)),
                    CholeskySymbolicParams {
                        supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
                        ..Default::default()
                    },
                )
            }
            _ => factorize_symbolic_cholesky(
                pattern,
                Side::Upper,
                SymmetricOrdering::Amd,
                CholeskySymbolicParams::default(),
            ),
        }
        .map_err(|e| self.err(&format!("sparse symbolic analysis failed: {e:?}")))?;
        self.l_values.clear();
        self.l_values.resize(symbolic.len_val(), 0.0);
        let par = Par::Seq;
        let req = symbolic
            .factorize_numeric_llt_scratch::<f64>(par, Default::default())
            .or(symbolic.solve_in_place_scratch::<f64>(self.nrhs, par));
        self.symbolic = Some(symbolic);
        Ok(req)
    }

    /// AMD ordering of the block graph (`n` nodes instead of `dim`), expanded block-wise
    /// into a scalar permutation and its inverse.
    fn block_amd_permutation(&self) -> Result<(Vec<usize>, Vec<usize>), CoreError> {
        let n = self.n;
        let blk_row: Vec<usize> = self.blk_row.iter().map(|&r| r as usize).collect();
        let blk_pattern =
            SymbolicSparseColMatRef::new_checked(n, n, &self.blk_start, None, &blk_row);
        let mut bperm = vec![0usize; n];
        let mut bperm_inv = vec![0usize; n];
        let mut amd_mem = MemBuffer::try_new(amd::order_scratch::<usize>(n, blk_row.len()))
            .map_err(|_| self.err("out of memory"))?;
        amd::order(
            &mut bperm,
            &mut bperm_inv,
            blk_pattern,
            amd::Control::default(),
            MemStack::new(&mut amd_mem),
        )
        .map_err(|e| self.err(&format!("AMD ordering failed: {e:?}")))?;
        let dim = self.dim();
        let mut perm = vec![0usize; dim];
        let mut perm_inv = vec![0usize; dim];
        let mut new = 0;
        for &b in &bperm {
            for a in 0..self.size(b) {
                perm[new] = self.offset[b] + a;
                perm_inv[self.offset[b] + a] = new;
                new += 1;
            }
        }
        Ok((perm, perm_inv))
    }

    /// Number of block rows.
    #[inline]
    pub fn n(&self) -> usize {
        self.n
    }

    /// Number of scalar unknowns.
    #[inline]
    pub fn dim(&self) -> usize {
        self.offset[self.offset.len() - 1]
    }

    /// Unknowns of block row `i`.
    #[inline]
    pub fn size(&self, i: usize) -> usize {
        self.offset[i + 1] - self.offset[i]
    }

    /// First scalar unknown of block row `i`.
    #[inline]
    pub fn offset(&self, i: usize) -> usize {
        self.offset[i]
    }

    /// The factorisation chosen at setup.
    pub fn factorization(&self) -> Factorization {
        self.factorization
    }

    /// Zeroes all blocks and right-hand sides.
    pub fn clear(&mut self) {
        self.blocks.iter_mut().for_each(|v| *v = 0.0);
        self.rhs.iter_mut().for_each(|v| *v = 0.0);
    }

    /// Index of the stored block `(min(i, j), max(i, j))`, if it is in the pattern.
    #[inline]
    pub fn block_index(&self, i: usize, j: usize) -> Option<usize> {
        let (i, j) = (i.min(j), i.max(j));
        let (s, e) = (self.blk_start[j], self.blk_start[j + 1]);
        self.blk_row[s..e]
            .binary_search(&(i as u32))
            .ok()
            .map(|k| s + k)
    }

    /// Index of the diagonal block `(j, j)` (always present: the last of its column).
    #[inline]
    pub fn diag_index(&self, j: usize) -> usize {
        self.blk_start[j + 1] - 1
    }

    /// Values of stored block `k` (`rows x cols`, column-major: `(a, b)` at `a + rows b`).
    #[inline]
    pub fn block_values_mut(&mut self, k: usize) -> &mut [f64] {
        let len = self.size(self.blk_row[k] as usize) * self.size(self.blk_col[k] as usize);
        &mut self.blocks[self.blk_off[k]..self.blk_off[k] + len]
    }

    /// Stored block `k` as an `R x C` matrix view. Panics when the block is not `R x C`.
    #[inline]
    pub fn block_mut<const R: usize, const C: usize>(
        &mut self,
        k: usize,
    ) -> SMatrixViewMut<'_, f64, R, C> {
        assert!(
            self.size(self.blk_row[k] as usize) == R && self.size(self.blk_col[k] as usize) == C,
            "block {k} is not {R}x{C}"
        );
        SMatrixViewMut::from_slice(&mut self.blocks[self.blk_off[k]..self.blk_off[k] + R * C])
    }

    /// Adds `m` (`rows x cols` of block `k`, column-major) to block `k`, or adds `mᵀ` when
    /// `transpose` (`m` is then the `(j, i)` block of a pair stored as `(i, j)`).
    #[inline]
    pub fn add_block(&mut self, k: usize, m: &[f64], transpose: bool) {
        let rows = self.size(self.blk_row[k] as usize);
        let dst = self.block_values_mut(k);
        if transpose {
            let cols = dst.len() / rows.max(1);
            for b in 0..cols {
                for a in 0..rows {
                    dst[a + rows * b] += m[b + cols * a];
                }
            }
        } else {
            for (d, v) in dst.iter_mut().zip(m) {
                *d += v;
            }
        }
    }

    /// Adds the `R x C` block `m` of `H` at block row `i`, block column `j` (either triangle:
    /// stored transposed when `i > j`). The assembly primitive of a factor: `m = Jᵢᵀ Ω Jⱼ`.
    /// Errors when `(i, j)` is not in the pattern or the sizes do not match.
    pub fn add_to_block<const R: usize, const C: usize>(
        &mut self,
        i: usize,
        j: usize,
        m: &SMatrix<f64, R, C>,
    ) -> Result<(), CoreError> {
        if i >= self.n || j >= self.n || self.size(i) != R || self.size(j) != C {
            return Err(CoreError::InvalidArgument(format!(
                "{}: block ({i}, {j}) is not {R}x{C}",
                self.name
            )));
        }
        let k = self
            .block_index(i, j)
            .ok_or_else(|| self.err(&format!("block ({i}, {j}) is not in the pattern")))?;
        self.add_block(k, m.as_slice(), i > j);
        Ok(())
    }

    /// Block row `i` of right-hand side `c`.
    #[inline]
    pub fn rhs_mut(&mut self, i: usize, c: usize) -> &mut [f64] {
        let off = c * self.dim() + self.offset[i];
        let len = self.size(i);
        &mut self.rhs[off..off + len]
    }

    /// Block row `i` of the first right-hand side as a vector view (`R` = its size).
    #[inline]
    pub fn rhs_block_mut<const R: usize>(&mut self, i: usize) -> SMatrixViewMut<'_, f64, R, 1> {
        assert!(self.size(i) == R, "block row {i} is not of size {R}");
        let off = self.offset[i];
        SMatrixViewMut::from_slice(&mut self.rhs[off..off + R])
    }

    /// Adds `v` to block row `i` of right-hand side `c`.
    #[inline]
    pub fn add_rhs(&mut self, i: usize, c: usize, v: &[f64]) {
        for (d, x) in self.rhs_mut(i, c).iter_mut().zip(v) {
            *d += x;
        }
    }

    /// The right-hand sides (`dim x nrhs`, column-major).
    #[inline]
    pub fn rhs(&self) -> &[f64] {
        &self.rhs
    }

    /// The solution of the last [`Self::solve`] (same layout as [`Self::rhs`]).
    #[inline]
    pub fn x(&self) -> &[f64] {
        &self.x
    }

    /// Block row `i` of the first solution column (`R` = its size).
    #[inline]
    pub fn x_block<const R: usize>(&self, i: usize) -> SVector<f64, R> {
        assert!(self.size(i) == R, "block row {i} is not of size {R}");
        SVector::from_column_slice(&self.x[self.offset[i]..self.offset[i] + R])
    }

    /// Solves `H x = rhs` into [`Self::x`].
    pub fn solve(&mut self) -> Result<(), CoreError> {
        self.solve_shifted(None)
    }

    /// Solves `(H + λI) x = rhs` into [`Self::x`] (`shift = Some(λ)`; `None` solves `H`).
    /// Errors (no panic) when the matrix is not numerically positive definite, the solution
    /// is not finite or the system was not set up.
    pub fn solve_shifted(&mut self, shift: Option<f64>) -> Result<(), CoreError> {
        let dim = self.dim();
        if dim == 0 {
            return Ok(());
        }
        for c in 0..self.nrhs {
            for r in 0..dim {
                self.rhs_mat[(r, c)] = self.rhs[c * dim + r];
            }
        }
        match self.factorization {
            Factorization::Dense => self.factor_solve_dense(shift)?,
            _ => self.factor_solve_sparse(shift)?,
        }
        for c in 0..self.nrhs {
            for r in 0..dim {
                self.x[c * dim + r] = self.rhs_mat[(r, c)];
            }
        }
        if self.x.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(self.err("non-finite solution"))
        }
    }

    fn factor_solve_sparse(&mut self, shift: Option<f64>) -> Result<(), CoreError> {
        for (v, &s) in self.values.iter_mut().zip(&self.src) {
            *v = self.blocks[s];
        }
        if let Some(l) = shift {
            for &p in &self.diag_pos {
                self.values[p] += l;
            }
        }
        let name = self.name;
        let dim = self.dim();
        let (Some(mem), Some(symbolic)) = (self.mem.as_mut(), self.symbolic.as_ref()) else {
            return Err(CoreError::Degenerate(format!("{name}: solve before setup")));
        };
        let par = Par::Seq;
        let stack = MemStack::new(mem);
        let pattern =
            SymbolicSparseColMatRef::new_checked(dim, dim, &self.col_ptr, None, &self.row_idx);
        let a = SparseColMatRef::new(pattern, &self.values);
        let l = symbolic
            .factorize_numeric_llt(
                &mut self.l_values,
                a,
                Side::Upper,
                Default::default(),
                par,
                stack,
                Default::default(),
            )
            .map_err(|_| CoreError::Degenerate(format!("{name}: matrix not positive definite")))?;
        l.solve_in_place_with_conj(Conj::No, self.rhs_mat.as_mut(), par, stack);
        Ok(())
    }

    fn factor_solve_dense(&mut self, shift: Option<f64>) -> Result<(), CoreError> {
        // The factorisation overwrites the lower triangle, fill-in included: clear it so
        // that entries outside the pattern are zero again.
        self.dense.as_mut().fill(0.0);
        for j in 0..self.n {
            let (oj, cols) = (self.offset[j], self.size(j));
            for k in self.blk_start[j]..self.blk_start[j + 1] {
                let i = self.blk_row[k] as usize;
                let (oi, rows) = (self.offset[i], self.size(i));
                let blk = &self.blocks[self.blk_off[k]..self.blk_off[k] + rows * cols];
                for b in 0..cols {
                    for a in 0..rows {
                        // Both triangles (the factorisation reads the lower one).
                        self.dense[(oi + a, oj + b)] = blk[a + rows * b];
                        self.dense[(oj + b, oi + a)] = blk[a + rows * b];
                    }
                }
            }
        }
        if let Some(l) = shift {
            for d in 0..self.dim() {
                self.dense[(d, d)] += l;
            }
        }
        let name = self.name;
        let Some(mem) = self.mem.as_mut() else {
            return Err(CoreError::Degenerate(format!("{name}: no workspace")));
        };
        let par = Par::Seq;
        let stack = MemStack::new(mem);
        llt::factor::cholesky_in_place(
            self.dense.as_mut(),
            Default::default(),
            par,
            stack,
            Default::default(),
        )
        .map_err(|_| CoreError::Degenerate(format!("{name}: matrix not positive definite")))?;
        llt::solve::solve_in_place(self.dense.as_ref(), self.rhs_mat.as_mut(), par, stack);
        Ok(())
    }
}

impl std::fmt::Debug for BlockSparseSystem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlockSparseSystem")
            .field("name", &self.name)
            .field("n", &self.n)
            .field("dim", &self.dim())
            .field("blocks", &self.blk_row.len())
            .field("factorization", &self.factorization)
            .field("nnz", &self.values.len())
            .field("factor_nnz", &self.l_values.len())
            .field("scratch_bytes", &self.mem_bytes)
            .finish()
    }
}

#[cfg(test)]
#[path = "block_sparse_tests.rs"]
mod tests;
