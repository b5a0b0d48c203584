use nalgebra::{DMatrix, DVector, SMatrix};

use super::*;

/// A deterministic pseudo-random number in [-1, 1).
fn rnd(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

/// Fills `sys` with a random symmetric positive definite matrix on its pattern (every
/// stored block plus a dominant diagonal) and random right-hand sides; returns the dense
/// matrix and right-hand sides.
fn fill_random(sys: &mut BlockSparseSystem, seed: u64) -> (DMatrix<f64>, DMatrix<f64>) {
    let mut s = seed;
    let dim = sys.dim();
    let nrhs = sys.rhs().len() / dim;
    let mut h = DMatrix::zeros(dim, dim);
    sys.clear();
    for j in 0..sys.n() {
        for i in 0..=j {
            let Some(k) = sys.block_index(i, j) else {
                continue;
            };
            let (ri, cj) = (sys.size(i), sys.size(j));
            let mut m: Vec<f64> = (0..ri * cj).map(|_| rnd(&mut s)).collect();
            if i == j {
                for b in 0..cj {
                    for a in 0..b {
                        m[b + ri * a] = m[a + ri * b];
                    }
                    m[b + ri * b] = 10.0 * dim as f64;
                }
            }
            for b in 0..cj {
                for a in 0..ri {
                    let v = m[a + ri * b];
                    h[(sys.offset(i) + a, sys.offset(j) + b)] = v;
                    h[(sys.offset(j) + b, sys.offset(i) + a)] = v;
                }
            }
            sys.add_block(k, &m, false);
        }
    }
    let mut r = DMatrix::zeros(dim, nrhs);
    for c in 0..nrhs {
        for i in 0..sys.n() {
            let v: Vec<f64> = (0..sys.size(i)).map(|_| rnd(&mut s)).collect();
            sys.add_rhs(i, c, &v);
            for (a, x) in v.iter().enumerate() {
                r[(sys.offset(i) + a, c)] = *x;
            }
        }
    }
    (h, r)
}

fn check_solution(sys: &BlockSparseSystem, h: &DMatrix<f64>, r: &DMatrix<f64>, shift: f64) {
    let dim = sys.dim();
    let x = DMatrix::from_column_slice(dim, r.ncols(), sys.x());
    let res = (h + DMatrix::identity(dim, dim) * shift) * x - r;
    assert!(res.amax() < 1e-10, "residual {}", res.amax());
}

#[test]
fn mixed_block_sizes_solve_with_every_factorization() {
    // Pose (6) and velocity-bias (9) blocks of three keyframes, a 7-dof block and a 1-dof
    // block: a chain with a far link (fill-in outside the pattern).
    let sizes = [6, 9, 6, 9, 6, 9, 7, 1];
    let links = [
        (0, 1),
        (1, 2),
        (2, 3),
        (3, 4),
        (4, 5),
        (0, 2),
        (2, 4),
        (6, 0),
        (7, 6),
        (7, 4),
    ];
    for f in [
        Factorization::Dense,
        Factorization::SparseScalarAmd,
        Factorization::SparseBlockAmd,
    ] {
        let mut sys = BlockSparseSystem::new("test");
        let mut pairs: Vec<(u32, u32)> = links.iter().map(|&(a, b)| (a, b)).collect();
        sys.setup(&sizes, 2, &mut pairs, f).unwrap();
        assert_eq!(sys.dim(), 53);
        // Several solves with new values reuse the factorisation workspace.
        for seed in 1..4 {
            let (h, r) = fill_random(&mut sys, seed);
            sys.solve().unwrap();
            check_solution(&sys, &h, &r, 0.0);
            sys.solve_shifted(Some(0.5)).unwrap();
            check_solution(&sys, &h, &r, 0.5);
        }
    }
}

#[test]
fn add_to_block_stores_the_upper_triangle() {
    let mut sys = BlockSparseSystem::new("test");
    let mut pairs = vec![(1, 0)];
    sys.setup(&[2, 3], 1, &mut pairs, Factorization::Dense)
        .unwrap();
    let m = SMatrix::<f64, 3, 2>::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0);
    // Block (1, 0) is stored as (0, 1) = mᵀ.
    sys.add_to_block(1, 0, &m).unwrap();
    let k = sys.block_index(0, 1).unwrap();
    assert_eq!(sys.block_mut::<2, 3>(k).into_owned(), m.transpose());
    assert!(sys.add_to_block(0, 1, &m).is_err());
    sys.add_to_block(0, 0, &SMatrix::<f64, 2, 2>::identity())
        .unwrap();
    sys.add_to_block(1, 1, &(SMatrix::<f64, 3, 3>::identity() * 100.0))
        .unwrap();
    sys.rhs_block_mut::<2>(0).copy_from_slice(&[1.0, 2.0]);
    sys.rhs_mut(1, 0).copy_from_slice(&[3.0, 4.0, 5.0]);
    sys.solve().unwrap();
    let mut h = DMatrix::<f64>::zeros(5, 5);
    h.view_mut((0, 0), (2, 2)).fill_with_identity();
    h.view_mut((2, 2), (3, 3))
        .copy_from(&(SMatrix::<f64, 3, 3>::identity() * 100.0));
    h.view_mut((2, 0), (3, 2)).copy_from(&m);
    h.view_mut((0, 2), (2, 3)).copy_from(&m.transpose());
    let x = DVector::from_column_slice(sys.x());
    let r = DVector::from_column_slice(&[1.0, 2.0, 3.0, 4.0, 5.0]);
    assert!((h * x - r).amax() < 1e-12);
    assert_eq!(sys.x_block::<2>(0).as_slice(), &sys.x()[..2]);
}

#[test]
fn not_positive_definite_is_an_error() {
    let mut sys = BlockSparseSystem::new("test");
    for f in [Factorization::Dense, Factorization::SparseBlockAmd] {
        sys.setup_uniform(2, 2, 1, &mut vec![(0, 1)], f).unwrap();
        sys.add_block(sys.diag_index(0), &[1.0, 0.0, 0.0, -1.0], false);
        sys.add_block(sys.diag_index(1), &[1.0, 0.0, 0.0, 1.0], false);
        let e = sys.solve().unwrap_err();
        assert!(
            format!("{e}").contains("test: matrix not positive definite"),
            "{e}"
        );
    }
    let mut pairs = vec![(0, 5)];
    assert!(sys
        .setup_uniform(2, 2, 1, &mut pairs, Factorization::Dense)
        .is_err());
}
