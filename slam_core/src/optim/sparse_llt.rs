//! The numeric half of a sparse Cholesky solve, shared by bundle adjustment's reduced
//! camera system and the pose-graph optimiser's normal equations: both keep the upper
//! triangle of a symmetric matrix in compressed columns with a symbolic factorisation made
//! once, and factorise and solve in place at every iteration (no allocation).
use faer::dyn_stack::MemStack;
use faer::sparse::linalg::cholesky::SymbolicCholesky;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side};

/// Factorises the `dim × dim` matrix (upper triangle in `col_ptr` / `row_idx` / `values`)
/// into `l_values` and solves `rhs` in place. `Err(())` when the matrix is not positive
/// definite (the caller names the system in its error).
#[allow(clippy::too_many_arguments)]
pub(crate) fn factor_solve_upper(
    symbolic: &SymbolicCholesky<usize>,
    dim: usize,
    col_ptr: &[usize],
    row_idx: &[usize],
    values: &[f64],
    l_values: &mut [f64],
    rhs: MatMut<'_, f64>,
    stack: &mut MemStack,
) -> Result<(), ()> {
    let par = Par::Seq;
    let pattern = SymbolicSparseColMatRef::new_checked(dim, dim, col_ptr, None, row_idx);
    let a = SparseColMatRef::new(pattern, values);
    let l = symbolic
        .factorize_numeric_llt(
            l_values,
            a,
            Side::Upper,
            Default::default(),
            par,
            stack,
            Default::default(),
        )
        .map_err(|_| ())?;
    l.solve_in_place_with_conj(Conj::No, rhs, par, stack);
    Ok(())
}
