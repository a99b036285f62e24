//! The classical two-view oracle recovers generated camera trajectories (known poses) to within
//! a few degrees of rotation. Prints its Rac/Tac at 5 degrees. Translation directions of the
//! shortest pairs (5-12 cm apart, a few pixels of parallax at 192x192) are much less certain,
//! so only a loose bound is asserted on them.

use evaluation::metrics::{CameraMetrics, trajectory_errors};
use evaluation::oracle::{ClassicalOracle, ClassicalSettings, PoseOracle};
use trainer_core::scenes::{Scene, SceneConfig, Trajectory};

#[test]
fn classical_oracle_recovers_generated_trajectories() {
    let config = SceneConfig {
        image_size: 192,
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
    assert!(
        metrics.at(30).unwrap().translation_accuracy >= 0.6,
        "{metrics:?}"
    );
}
