//! The PTX ISA version a CUDA driver loads; cubecl-cuda puts it in its kernel cache's name.

use core::fmt;

/// A PTX ISA version written without its dot: PTX 8.7 is `PtxVersion(87)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PtxVersion(u32);

/// CUDA driver versions (as `cuDriverGetVersion` reports them: 12.8 is 12080) and the newest
/// PTX ISA each loads, newest driver first (NVIDIA's PTX ISA release notes).
const NEWEST_PTX_BY_DRIVER: [(i32, u32); 24] = [
    (13030, 93),
    (13020, 92),
    (13010, 91),
    (13000, 90),
    (12090, 88),
    (12080, 87),
    (12050, 85),
    (12040, 84),
    (12030, 83),
    (12020, 82),
    (12010, 81),
    (12000, 80),
    (11080, 78),
    (11070, 77),
    (11060, 76),
    (11050, 75),
    (11040, 74),
    (11030, 73),
    (11020, 72),
    (11010, 71),
    (11000, 70),
    (10020, 65),
    (10010, 64),
    (10000, 63),
];

impl PtxVersion {
    /// The newest PTX version a driver of CUDA `driver` loads; `None` before CUDA 10.0.
    pub fn for_driver(driver: i32) -> Option<Self> {
        NEWEST_PTX_BY_DRIVER
            .iter()
            .find(|(first_driver, _)| driver >= *first_driver)
            .map(|&(_, ptx)| Self(ptx))
    }
}

impl fmt::Display for PtxVersion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ptx{}", self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::PtxVersion;

    #[test]
    fn each_driver_gets_the_newest_ptx_it_loads() {
        assert_eq!(PtxVersion::for_driver(13000).map(|v| v.to_string()), Some("ptx90".into()));
        assert_eq!(PtxVersion::for_driver(12060).map(|v| v.to_string()), Some("ptx85".into()));
        assert_eq!(PtxVersion::for_driver(13990).map(|v| v.to_string()), Some("ptx93".into()));
        assert_eq!(PtxVersion::for_driver(9020), None);
    }
}
