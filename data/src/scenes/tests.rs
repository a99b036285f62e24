//! Scenes and trajectories: geometry, determinism, rendering.

use super::*;

fn mean_abs_diff(a: &Image, b: &Image) -> f64 {
    assert_eq!(a.pixels.len(), b.pixels.len());
    let total: f64 = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(x, y)| f64::from((x - y).abs()))
        .sum();
    total / a.pixels.len() as f64
}

fn apply(pose: &CameraPose, point: Vec3) -> Vec3 {
    add_scaled(rotate(&pose.rotation, point), pose.translation, 1.0)
}

#[test]
fn same_key_renders_identically_and_other_indices_differ() {
    let config = SceneConfig::default();
    let trajectory = Trajectory::random(11, 2, 4);
    assert_eq!(trajectory, Trajectory::random(11, 2, 4));
    assert_ne!(trajectory, Trajectory::random(11, 3, 4));
    let first = Scene::random(11, 2, &config).render_trajectory(&trajectory);
    let again = Scene::random(11, 2, &config).render_trajectory(&trajectory);
    assert_eq!(first, again);
    let other = Scene::random(11, 3, &config).render_trajectory(&trajectory);
    assert_ne!(first, other);
}

#[test]
fn relative_pose_of_itself_is_identity_and_composes() {
    let a = CameraPose::look_at([0.3, -0.2, -1.0], [1.0, 0.4, 3.0]).rolled(0.2);
    let b = CameraPose::look_at([-0.5, 0.1, -2.0], [-0.2, -0.3, 2.5]);
    let own = a.relative_to(&a);
    let identity = CameraPose::identity();
    for i in 0..3 {
        for j in 0..3 {
            assert!((own.rotation[i][j] - identity.rotation[i][j]).abs() < 1e-9);
        }
        assert!(own.translation[i].abs() < 1e-9);
    }
    // T_rel * T_b == T_a.
    let relative = a.relative_to(&b).matrix();
    let (ma, mb) = (a.matrix(), b.matrix());
    for i in 0..4 {
        for j in 0..4 {
            let value: f64 = (0..4).map(|k| relative[i][k] * mb[k][j]).sum();
            assert!((value - ma[i][j]).abs() < 1e-9, "entry ({i}, {j})");
        }
    }
}

#[test]
fn look_at_puts_the_target_on_the_optical_axis() {
    let center = [0.4, -0.3, -1.5];
    let target = [-1.0, 0.5, 3.0];
    let pose = CameraPose::look_at(center, target);
    let seen = apply(&pose, target);
    assert!(seen[0].abs() < 1e-9 && seen[1].abs() < 1e-9, "{seen:?}");
    assert!((seen[2] - norm(sub(target, center))).abs() < 1e-9);
    let origin = apply(&pose, center);
    assert!(origin.iter().all(|v| v.abs() < 1e-9));
    let recovered = pose.center();
    assert!((0..3).all(|k| (recovered[k] - center[k]).abs() < 1e-9));
    // World up (-y) appears above the target in the image (camera y < 0).
    let above = apply(&pose, [target[0], target[1] - 1.0, target[2]]);
    assert!(above[1] < 0.0);
    // Proper rotation.
    let r = pose.rotation;
    for (i, &row) in r.iter().enumerate() {
        for (j, &other) in r.iter().enumerate() {
            let expected = if i == j { 1.0 } else { 0.0 };
            assert!((dot(row, other) - expected).abs() < 1e-9);
        }
    }
    assert!((dot(cross(r[0], r[1]), r[2]) - 1.0).abs() < 1e-9);
    // Looking straight down +z from the origin is the identity.
    let straight = CameraPose::look_at([0.0; 3], [0.0, 0.0, 2.0]);
    let m = straight.matrix();
    let id = CameraPose::identity().matrix();
    for i in 0..4 {
        for j in 0..4 {
            assert!((m[i][j] - id[i][j]).abs() < 1e-12);
        }
    }
}

#[test]
fn render_has_the_right_size_and_range_and_is_not_constant() {
    let config = SceneConfig::default();
    let scene = Scene::random(5, 0, &config);
    let image = scene.render(&CameraPose::look_at([0.0, 0.0, -2.0], [0.0, 0.0, 3.0]));
    assert_eq!(image.height, 64);
    assert_eq!(image.width, 64);
    assert_eq!(image.pixels.len(), 64 * 64 * 3);
    assert!(image.pixels.iter().all(|v| (-1.0..=1.0).contains(v)));
    let low = image.pixels.iter().copied().fold(f32::INFINITY, f32::min);
    let high = image
        .pixels
        .iter()
        .copied()
        .fold(f32::NEG_INFINITY, f32::max);
    assert!(high - low > 0.3, "range {low}..{high}");

    let small = SceneConfig {
        image_size: 24,
        ..SceneConfig::default()
    };
    let image = Scene::random(5, 0, &small).render(&CameraPose::identity());
    assert_eq!((image.height, image.width), (24, 24));
    assert_eq!(image.pixels.len(), 24 * 24 * 3);
}

#[test]
fn trajectories_stay_in_the_camera_region() {
    for index in 0..200 {
        let trajectory = Trajectory::random(3, index, 12);
        assert_eq!(trajectory.poses.len(), 12);
        for pose in &trajectory.poses {
            let c = pose.center();
            for k in 0..3 {
                let allowed = (CAMERA_MIN[k] - 1e-9)..=(CAMERA_MAX[k] + 1e-9);
                assert!(allowed.contains(&c[k]), "index {index}: centre {c:?}");
            }
        }
    }
    assert!(Trajectory::random(3, 0, 0).poses.is_empty());
    assert_eq!(Trajectory::random(3, 0, 1).poses.len(), 1);
}

#[test]
fn consecutive_frames_differ_but_not_wildly() {
    let config = SceneConfig::default();
    for index in 0..6 {
        let scene = Scene::random(9, index, &config);
        let frames = scene.render_trajectory(&Trajectory::random(9, index, 8));
        assert_eq!(frames.len(), 8);
        for pair in frames.windows(2) {
            let diff = mean_abs_diff(&pair[0], &pair[1]);
            assert!(
                (0.005..0.5).contains(&diff),
                "index {index}: mean abs diff {diff}"
            );
        }
    }
}

#[test]
fn different_scenes_along_the_same_trajectory_differ() {
    let config = SceneConfig::default();
    let trajectory = Trajectory::random(1, 0, 4);
    let a = Scene::random(1, 0, &config).render_trajectory(&trajectory);
    let b = Scene::random(1, 1, &config).render_trajectory(&trajectory);
    for (x, y) in a.iter().zip(&b) {
        let diff = mean_abs_diff(x, y);
        assert!(diff > 0.05, "mean abs diff {diff}");
    }
}

#[test]
fn rendering_is_fast_enough_for_data_generation() {
    let config = SceneConfig::default();
    // Debug builds are far slower; the figure that matters is the release one.
    let count: u64 = if cfg!(debug_assertions) { 5 } else { 50 };
    let start = std::time::Instant::now();
    let mut checksum = 0.0;
    for index in 0..count {
        let scene = Scene::random(2, index, &config);
        let frames = scene.render_trajectory(&Trajectory::random(2, index, 8));
        checksum += frames.iter().map(|f| f64::from(f.pixels[0])).sum::<f64>();
    }
    println!(
        "rendered {count} trajectories x 8 frames of 64x64 in {:?} (checksum {checksum})",
        start.elapsed()
    );
}
