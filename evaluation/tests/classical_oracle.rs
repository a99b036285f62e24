//! The classical oracle recovers generated camera trajectories (known poses) to within a few
//! degrees of rotation and translation direction over all frame pairs; prints Rac/Tac@5.
//!
//! Setup: 8 scenes with 6 objects, 6-frame trajectories (5-12 cm between consecutive frames,
//! so the shortest pairs have only a few pixels of parallax), rendered at 256x256, the
//! resolution of the real data. At 192x192 the same pipeline's mean translation error is about
//! 5 degrees instead of about 2.6: parallax is measured in pixels, so resolution matters. On
//! other seeds most sequences stay around 2 degrees but an occasional one converges to a wrong
//! motion (e.g. one of 8 on seed 12), so these are the numbers of this seed, not a guarantee.

use data::scenes::{Scene, SceneConfig, Trajectory};
use evaluation::metrics::{CameraMetrics, trajectory_errors};
use evaluation::oracle::{ClassicalOracle, ClassicalSettings, PoseOracle};

#[test]
fn classical_oracle_recovers_generated_trajectories() {
    let config = SceneConfig {
        image_size: 256,
        objects: 6,
        ..SceneConfig::default()
    };
    let oracle = ClassicalOracle::new(ClassicalSettings::default());
    let mut errors = Vec::new();
    let mut failures = 0;
    for index in 0..8u64 {
        let scene = Scene::random(11, index, &config);
        let trajectory = Trajectory::random(11, index, 6);
        let frames = scene.render_trajectory(&trajectory);
        match oracle.estimate(&frames) {
            Ok(poses) => errors.extend(trajectory_errors(&trajectory.poses, &poses)),
            Err(error) => {
                println!("sequence {index}: {error}");
                failures += 1;
            }
        }
    }
    let metrics = CameraMetrics::from_errors(&errors);
    let at5 = metrics.at(5).unwrap();
    println!(
        "classical_oracle pairs={} failures={failures} Rac@5={:.3} Tac@5={:.3} AUC@30={:.3} mean_rot={:.2} mean_trans={:.2}",
        metrics.pairs,
        at5.rotation_accuracy,
        at5.translation_accuracy,
        metrics.at(30).unwrap().auc,
        metrics.mean_rotation_error,
        metrics.mean_translation_error
    );
    assert!(failures <= 1, "{failures} sequences failed");
    assert!(at5.rotation_accuracy >= 0.9, "{metrics:?}");
    assert!(metrics.mean_rotation_error < 3.0, "{metrics:?}");
    assert!(at5.translation_accuracy >= 0.8, "{metrics:?}");
    assert!(metrics.mean_translation_error < 5.0, "{metrics:?}");
}
