//! The probe CSV reader (`voxrad::output::probe::read_points_from`) on arbitrary bytes, and a
//! lookup of every point read in a small results set. Errors must name the file (and the line).
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::Path;
use voxrad::output::probe::{read_points_from, ProbeIndex};
use voxrad::output::results::{Record, Results, SideMaterial};
use voxrad::voxel::Grid;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("points.csv");
    match read_points_from(path, data) {
        Ok(points) => {
            let results = Results {
                grid: Grid {
                    origin: [-1.0, 0.0, 2.0],
                    voxel_size: 0.5,
                    dims: [4, 4, 4],
                },
                records: (0..4)
                    .map(|i| Record {
                        voxel: [i, 0, 1],
                        point: [0.5; 3],
                        normal: [0.0, 0.0, 1.0],
                        area: 1.0,
                        radiosity: [[1.0; 3], [0.5; 3]],
                        material: [0, 0],
                        extent: [[0.0; 3], [1.0; 3]],
                    })
                    .collect(),
                materials: vec![SideMaterial {
                    reflectance: [0.5, 0.0, 0.25],
                    emission: [0.0; 3],
                }],
            };
            let index = ProbeIndex::new(&results);
            for (p, n) in points {
                let row = index.lookup(p, n);
                assert!(row.radiosity.iter().all(|b| b.is_finite()), "{row:?}");
            }
        }
        Err(e) => assert!(e.to_string().contains("points.csv"), "{e}"),
    }
});
