//! The CPU backend's matrix product sums each entry in one order on every x86-64 CPU, whatever
//! its L1 cache, so a seed trains the same on any of them (vendor/gemm-common/README.md: the
//! transfer recipe's seed 8 took another path on an AMD EPYC than on the machine it was
//! measured on, while gemm split the inner dimension at 512 on one and 1024 on the other).
//!
//! gemm splits the inner dimension `k` into blocks and adds each block's partial sum into the
//! result. The product below tells the splits apart: its first row holds 2^25 at k = 0, -2^25
//! at k = 600 and 1.0 at k = 700. Summed in one block of 1000, 2^25 and -2^25 cancel before
//! the 1.0 arrives and the entry is 1.0; split into two blocks of 500, the second block's
//! -2^25 + 1.0 rounds to -2^25 and the entry is 0.0.

use burn::tensor::{Device, Tensor, TensorData};

/// More than 64 rows, so gemm sizes its blocks from the cache (it uses fixed blocks of at most
/// 512 below that).
const ROWS: usize = 128;
const INNER: usize = 1000;
const COLUMNS: usize = 8;

/// 2^25, where adding 1.0 to an f32 rounds back to the same value.
const BIG: f32 = 33_554_432.0;

fn telling_product() -> Vec<f32> {
    let device = Device::flex();
    let mut lhs = vec![0.0; ROWS * INNER];
    lhs[0] = BIG;
    lhs[600] = -BIG;
    lhs[700] = 1.0;
    let lhs = Tensor::<2>::from_data(TensorData::new(lhs, [ROWS, INNER]), &device);
    let rhs = Tensor::<2>::ones([INNER, COLUMNS], &device);
    lhs.matmul(rhs)
        .into_data()
        .try_to_vec::<f32>()
        .expect("an f32 product")
}

#[test]
fn an_inner_dimension_of_1000_is_summed_in_one_block_on_every_cpu() {
    let product = telling_product();
    assert_eq!(
        &product[..COLUMNS],
        &[1.0; COLUMNS],
        "one block of 1000 keeps the 1.0; 0.0 means gemm split k by this CPU's L1 cache"
    );
    assert!(
        product[COLUMNS..].iter().all(|&entry| entry == 0.0),
        "every other row is zero"
    );
}
