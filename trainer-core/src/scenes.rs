//! Procedural 3D scenes rendered from known camera poses.
//!
//! Pose-estimation training and evaluation need image sequences whose camera motion is known
//! exactly. This module ray-casts small textured rooms from given poses, so one camera
//! trajectory can be rendered in several different scenes: a pose representation that only
//! depends on the motion should then agree across them while the pixels differ.
//!
//! Conventions:
//! - Poses are world-to-camera (`x_cam = R * x_world + t`), OpenCV axes: x right, y down,
//!   z forward. The world's "up" is `-y`, so the floor is the room face at `y = +half_height`.
//! - Rooms are axis-aligned boxes centred on the origin. Every room contains the fixed camera
//!   region `x ∈ [-1.2, 1.2], y ∈ [-0.5, 0.5], z ∈ [-2.5, 0]` with at least a metre to spare,
//!   and no object comes closer than `z = 0.5`, so any [`Trajectory::random`] fits any
//!   [`Scene::random`] without passing through walls or objects.
//! - Every random choice comes from a [`Stream`] keyed by `(seed, index, ...)`, so scenes and
//!   trajectories are reproducible and independent of each other.

use std::array::from_fn;
use std::f64::consts::{PI, TAU};

use crate::augment::Image;
use crate::rng::Stream;

/// A point or direction in world or camera space.
type Vec3 = [f64; 3];

/// Stream key tag for a scene's room and wall textures.
const SCENE_TAG: u64 = 0x5343_454E_4553;
/// Stream key tag for one object of a scene (followed by the object's number).
const OBJECT_TAG: u64 = 0x4F42_4A45_4354;
/// Stream key tag for a camera trajectory.
const TRAJECTORY_TAG: u64 = 0x5452_414A;

/// The world's up direction (OpenCV-style worlds have y pointing down).
const WORLD_UP: Vec3 = [0.0, -1.0, 0.0];
/// 3x3 identity rotation.
const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Lower corner of the box that random camera centres stay in.
const CAMERA_MIN: Vec3 = [-1.2, -0.5, -2.5];
/// Upper corner of the box that random camera centres stay in.
const CAMERA_MAX: Vec3 = [1.2, 0.5, 0.0];
/// Largest sideways bulge of a trajectory's arc away from its straight chord.
const BEND: f64 = 0.15;
/// The point random trajectories initially look roughly toward.
const ROOM_FOCUS: Vec3 = [0.0, 0.0, 2.0];
/// Objects start at this z or beyond, clear of the camera region.
const OBJECT_MIN_Z: f64 = 0.5;
/// Objects stay within this |x| so most of them can be seen from the camera region.
const OBJECT_MAX_X: f64 = 2.2;

/// Unit direction toward the light (from above, slightly right and behind the camera).
const LIGHT: Vec3 = [0.36, -0.8, -0.48];
/// Light reaching surfaces facing away from [`LIGHT`].
const AMBIENT: f64 = 0.3;
/// Extra light reaching surfaces facing [`LIGHT`] (wrapped Lambert).
const DIFFUSE: f64 = 0.7;
/// Colour of rays that hit nothing (only possible with a camera outside the room).
const BACKGROUND: Vec3 = [0.5; 3];
/// Smallest accepted ray parameter and smallest usable vector length.
const EPSILON: f64 = 1e-9;

fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a + scale * b`.
fn add_scaled(a: Vec3, b: Vec3, scale: f64) -> Vec3 {
    [
        a[0] + scale * b[0],
        a[1] + scale * b[1],
        a[2] + scale * b[2],
    ]
}

fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|`, or `None` when `a` is too short to have a direction.
fn normalized(a: Vec3) -> Option<Vec3> {
    let length = norm(a);
    if length > EPSILON {
        Some(a.map(|v| v / length))
    } else {
        None
    }
}

/// `r * v`.
fn rotate(r: &[[f64; 3]; 3], v: Vec3) -> Vec3 {
    [dot(r[0], v), dot(r[1], v), dot(r[2], v)]
}

/// `r^T * v`.
fn rotate_transposed(r: &[[f64; 3]; 3], v: Vec3) -> Vec3 {
    from_fn(|k| r[0][k] * v[0] + r[1][k] * v[1] + r[2][k] * v[2])
}

/// World-to-camera rigid transform: `x_cam = rotation * x_world + translation`. The camera
/// looks down +z with x right and y down (OpenCV convention).
///
/// This is the ground truth the generated data carries: the renderer consumes it and pose
/// metrics compare predictions against it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    /// Rows are the camera's x (right), y (down) and z (forward) axes in world coordinates.
    pub rotation: [[f64; 3]; 3],
    /// The world origin in camera coordinates.
    pub translation: [f64; 3],
}

impl CameraPose {
    /// The camera at the world origin looking down world +z: the neutral element for
    /// composing and comparing poses.
    pub fn identity() -> Self {
        Self {
            rotation: IDENTITY,
            translation: [0.0; 3],
        }
    }

    /// The camera centre in world coordinates (`-R^T t`), which is where rays start and what
    /// trajectories are laid out in.
    pub fn center(&self) -> [f64; 3] {
        rotate_transposed(&self.rotation, self.translation).map(|v| -v)
    }

    /// Builds the world-to-camera pose of a camera at `center` looking at `target`, with the
    /// world's up being `-y` (so image rows run downward along world +y), because placing
    /// cameras by position and gaze is far easier than writing rotations by hand.
    ///
    /// Looking straight up or down (where "up" gives no roll reference) uses world +x as the
    /// camera's right; a `target` equal to `center` gives the identity orientation.
    pub fn look_at(center: [f64; 3], target: [f64; 3]) -> Self {
        let rotation = match normalized(sub(target, center)) {
            Some(forward) => {
                let right = normalized(cross(forward, WORLD_UP)).unwrap_or([1.0, 0.0, 0.0]);
                let down = cross(forward, right);
                [right, down, forward]
            }
            None => IDENTITY,
        };
        let translation = rotate(&rotation, center).map(|v| -v);
        Self {
            rotation,
            translation,
        }
    }

    /// The 4x4 row-major world-to-camera matrix, for consumers that work with homogeneous
    /// matrices (metrics, serialisation, model conditioning).
    pub fn matrix(&self) -> [[f64; 4]; 4] {
        let r = self.rotation;
        let t = self.translation;
        from_fn(|i| {
            if i < 3 {
                [r[i][0], r[i][1], r[i][2], t[i]]
            } else {
                [0.0, 0.0, 0.0, 1.0]
            }
        })
    }

    /// The relative pose `T_self * inv(T_other)`: the camera metric convention of the spec,
    /// which maps `other`'s camera coordinates to `self`'s and so is independent of the
    /// choice of world frame.
    pub fn relative_to(&self, other: &CameraPose) -> CameraPose {
        let rotation: [[f64; 3]; 3] =
            from_fn(|i| from_fn(|j| dot(self.rotation[i], other.rotation[j])));
        let moved = rotate(&rotation, other.translation);
        CameraPose {
            rotation,
            translation: sub(self.translation, moved),
        }
    }

    /// The same camera rotated by `angle` radians about its optical axis.
    fn rolled(self, angle: f64) -> Self {
        let (s, c) = angle.sin_cos();
        let [r0, r1, r2] = self.rotation;
        let [t0, t1, t2] = self.translation;
        Self {
            rotation: [
                from_fn(|k| c * r0[k] - s * r1[k]),
                from_fn(|k| s * r0[k] + c * r1[k]),
                r2,
            ],
            translation: [c * t0 - s * t1, s * t0 + c * t1, t2],
        }
    }
}

/// A camera path, one pose per frame: the unit of known motion that is rendered, possibly
/// in several scenes.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// World-to-camera pose of each frame, in order.
    pub poses: Vec<CameraPose>,
}

/// A magnitude uniform in `[low, high)` with a random sign.
fn signed(stream: &mut Stream, low: f64, high: f64) -> f64 {
    let magnitude = stream.uniform_in(low, high);
    if stream.bernoulli(0.5) {
        magnitude
    } else {
        -magnitude
    }
}

impl Trajectory {
    /// A smooth random camera motion, deterministic from `(seed, index)`, so that training
    /// and evaluation sequences come with exact poses.
    ///
    /// The centre moves along a gently bent arc (mostly horizontal, 5-12 cm per frame, less
    /// when the path would leave the camera region) while yaw, pitch and roll drift linearly;
    /// frames are evenly spaced. The camera starts looking roughly toward the middle of the
    /// room's far half, so consecutive frames differ visibly but always see the room. All
    /// centres stay in the fixed camera region that every [`Scene`] keeps clear, so one
    /// trajectory can be rendered in any scene. The random draws do not depend on `frames`.
    pub fn random(seed: u64, index: u64, frames: usize) -> Self {
        let mut stream = Stream::new(&[seed, index, TRAJECTORY_TAG]);
        let direction = normalized([stream.normal(), 0.3 * stream.normal(), stream.normal()])
            .unwrap_or([1.0, 0.0, 0.0]);
        let sideways = normalized(cross(direction, WORLD_UP)).unwrap_or([1.0, 0.0, 0.0]);
        let bend = stream.uniform_in(-BEND, BEND);
        let step = stream.uniform_in(0.05, 0.12);

        // The chord stays in the camera region shrunk by the bend, so the arc stays in it.
        let low = CAMERA_MIN.map(|v| v + BEND);
        let high = CAMERA_MAX.map(|v| v - BEND);
        let reach = (0..3)
            .filter(|&k| direction[k].abs() > EPSILON)
            .map(|k| (high[k] - low[k]) / direction[k].abs())
            .fold(f64::INFINITY, f64::min);
        let spans = frames.saturating_sub(1) as f64;
        let length = (step * spans).min(reach);
        let start: Vec3 = from_fn(|k| {
            let travel = direction[k] * length;
            stream.uniform_in(low[k] - travel.min(0.0), high[k] - travel.max(0.0))
        });

        let toward_room = (ROOM_FOCUS[0] - start[0]).atan2(ROOM_FOCUS[2] - start[2]);
        let yaw = toward_room + stream.uniform_in(-0.25, 0.25);
        let pitch = stream.uniform_in(-0.12, 0.12);
        let roll = stream.uniform_in(-0.03, 0.03);
        let yaw_turn = (signed(&mut stream, 0.008, 0.03) * spans).clamp(-0.35, 0.35);
        let pitch_turn = (stream.uniform_in(-0.01, 0.01) * spans).clamp(-0.2, 0.2);
        let roll_turn = (stream.uniform_in(-0.004, 0.004) * spans).clamp(-0.06, 0.06);

        let poses = (0..frames)
            .map(|frame| {
                let u = if spans > 0.0 {
                    frame as f64 / spans
                } else {
                    0.0
                };
                let along = add_scaled(start, direction, length * u);
                let center = add_scaled(along, sideways, bend * (PI * u).sin());
                let yaw = yaw + yaw_turn * u;
                let pitch = pitch + pitch_turn * u;
                let forward = [
                    yaw.sin() * pitch.cos(),
                    -pitch.sin(),
                    yaw.cos() * pitch.cos(),
                ];
                CameraPose::look_at(center, add_scaled(center, forward, 1.0))
                    .rolled(roll + roll_turn * u)
            })
            .collect();
        Self { poses }
    }
}

/// Knobs for scene generation, kept apart from the seed so one configuration can generate
/// many scenes.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneConfig {
    /// Side of the square rendered images, in pixels.
    pub image_size: usize,
    /// Field of view (horizontal = vertical), in degrees; must lie in `(0, 180)`.
    pub fov_degrees: f64,
    /// Number of boxes and spheres placed in the room.
    pub objects: usize,
}

impl Default for SceneConfig {
    /// 64x64 images, a 60° field of view and 4 objects: small enough to render hundreds of
    /// sequences in seconds, rich enough for clear parallax.
    fn default() -> Self {
        Self {
            image_size: 64,
            fov_degrees: 60.0,
            objects: 4,
        }
    }
}

/// How a texture turns a point into a blend weight between its two colours.
#[derive(Debug, Clone, Copy)]
enum Pattern {
    /// Soft-edged parallel stripes across this unit direction.
    Stripes { direction: Vec3 },
    /// A soft checkerboard (3D on spheres, 2D on flat faces).
    Checkers,
    /// Three octaves of value noise: smooth blotches and gradients.
    Noise { seed: u64 },
}

/// A procedural two-colour texture.
#[derive(Debug, Clone)]
struct Texture {
    pattern: Pattern,
    /// Stripe period, checker cell side or noise cell side, in metres.
    period: f64,
    /// Shift of the pattern so textures do not all line up with the origin (z stays 0 so
    /// flat faces, textured at z = 0, see the full checker contrast).
    offset: Vec3,
    colours: [Vec3; 2],
}

/// An RGB colour in `[0, 1]` from hue (turns), saturation and value.
fn hsv(hue: f64, saturation: f64, value: f64) -> Vec3 {
    let h6 = hue.rem_euclid(1.0) * 6.0;
    let sector = h6.floor();
    let f = h6 - sector;
    let p = value * (1.0 - saturation);
    let q = value * (1.0 - saturation * f);
    let t = value * (1.0 - saturation * (1.0 - f));
    match sector as u32 {
        0 => [value, t, p],
        1 => [q, value, p],
        2 => [p, value, t],
        3 => [p, q, value],
        4 => [t, p, value],
        _ => [value, p, q],
    }
}

/// SplitMix64's finaliser, for hashing noise lattice points.
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A pseudo-random value in `[0, 1)` attached to an integer lattice point.
fn lattice(seed: u64, x: i64, y: i64, z: i64) -> f64 {
    let mut h = mix64(seed ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    h = mix64(h ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
    h = mix64(h ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9));
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

/// Smoothly interpolated lattice noise in `[0, 1)` with unit cells.
fn value_noise(seed: u64, p: Vec3) -> f64 {
    let cell = p.map(f64::floor);
    let s: Vec3 = from_fn(|k| {
        let f = p[k] - cell[k];
        f * f * (3.0 - 2.0 * f)
    });
    let [x, y, z] = cell.map(|v| v as i64);
    let corner = |dx: i64, dy: i64, dz: i64| {
        lattice(
            seed,
            x.wrapping_add(dx),
            y.wrapping_add(dy),
            z.wrapping_add(dz),
        )
    };
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), s[0]);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), s[0]);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), s[0]);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), s[0]);
    lerp(lerp(x00, x10, s[1]), lerp(x01, x11, s[1]), s[2])
}

/// Three octaves of value noise, normalised back to `[0, 1)`.
fn fractal_noise(seed: u64, p: Vec3) -> f64 {
    let mut sum = 0.0;
    let mut total = 0.0;
    let mut amplitude = 1.0;
    let mut frequency = 1.0;
    for octave in 0..3u64 {
        sum += amplitude * value_noise(seed.wrapping_add(octave), p.map(|v| v * frequency));
        total += amplitude;
        amplitude *= 0.5;
        frequency *= 2.0;
    }
    sum / total
}

impl Texture {
    /// A random texture whose pattern scale lies in `[period_low, period_high)` metres.
    fn random(stream: &mut Stream, period_low: f64, period_high: f64) -> Self {
        // One light and one dark colour with unrelated hues, in random order, so every
        // texture has strong contrast.
        let light_hue = stream.uniform();
        let dark_hue = light_hue + stream.uniform_in(0.15, 0.85);
        let light = hsv(
            light_hue,
            stream.uniform_in(0.2, 0.9),
            stream.uniform_in(0.65, 1.0),
        );
        let dark = hsv(
            dark_hue,
            stream.uniform_in(0.3, 1.0),
            stream.uniform_in(0.1, 0.45),
        );
        let colours = if stream.bernoulli(0.5) {
            [light, dark]
        } else {
            [dark, light]
        };
        let period = stream.uniform_in(period_low, period_high);
        let offset = [
            stream.uniform_in(-50.0, 50.0),
            stream.uniform_in(-50.0, 50.0),
            0.0,
        ];
        let pattern = match stream.below(3) {
            0 => {
                let angle = stream.uniform_in(0.0, TAU);
                let tilt = stream.uniform_in(-0.6, 0.6);
                Pattern::Stripes {
                    direction: [
                        angle.cos() * tilt.cos(),
                        angle.sin() * tilt.cos(),
                        tilt.sin(),
                    ],
                }
            }
            1 => Pattern::Checkers,
            _ => Pattern::Noise {
                seed: stream.next_u64(),
            },
        };
        Self {
            pattern,
            period,
            offset,
            colours,
        }
    }

    /// The colour in `[0, 1]` at a texture-space point (flat faces pass `(u, v, 0)`).
    fn colour(&self, point: Vec3) -> Vec3 {
        let p = add_scaled(point, self.offset, 1.0);
        let weight = match self.pattern {
            Pattern::Stripes { direction } => {
                0.5 + 1.5 * (dot(p, direction) * (TAU / self.period)).sin()
            }
            Pattern::Checkers => {
                let k = PI / self.period;
                0.5 + 2.5 * ((p[0] * k).sin() * (p[1] * k).sin() * (p[2] * k).cos())
            }
            Pattern::Noise { seed } => {
                let n = fractal_noise(seed, p.map(|v| v / self.period));
                0.5 + 2.5 * (n - 0.5)
            }
        }
        .clamp(0.0, 1.0);
        let [a, b] = self.colours;
        from_fn(|k| lerp(a[k], b[k], weight))
    }
}

/// The geometry of one object.
#[derive(Debug, Clone, Copy)]
enum Shape {
    /// An axis-aligned box between two corners.
    Cuboid { min: Vec3, max: Vec3 },
    /// A sphere.
    Sphere { center: Vec3, radius: f64 },
}

/// A textured object inside the room.
#[derive(Debug, Clone)]
struct Object {
    shape: Shape,
    texture: Texture,
}

impl Object {
    /// A random box or sphere in front of the camera region, resting on the floor or
    /// floating.
    fn random(stream: &mut Stream, half: Vec3) -> Self {
        let texture = Texture::random(stream, 0.15, 0.5);
        let cuboid = stream.bernoulli(0.5);
        let extent = if cuboid {
            [
                stream.uniform_in(0.2, 0.7),
                stream.uniform_in(0.2, 0.8),
                stream.uniform_in(0.2, 0.7),
            ]
        } else {
            [stream.uniform_in(0.25, 0.7); 3]
        };
        let x_reach = (half[0] - extent[0]).min(OBJECT_MAX_X);
        let x = stream.uniform_in(-x_reach, x_reach);
        let z = stream.uniform_in(OBJECT_MIN_Z + extent[2], half[2] - extent[2]);
        let floor = half[1] - extent[1];
        let y = if stream.bernoulli(0.6) {
            floor
        } else {
            stream.uniform_in(-floor, floor)
        };
        let center = [x, y, z];
        let shape = if cuboid {
            Shape::Cuboid {
                min: sub(center, extent),
                max: add_scaled(center, extent, 1.0),
            }
        } else {
            Shape::Sphere {
                center,
                radius: extent[0],
            }
        };
        Self { shape, texture }
    }
}

/// What a ray hit first.
#[derive(Debug, Clone, Copy)]
enum Hit {
    Nothing,
    /// The room face perpendicular to `axis` that the ray travels toward.
    Room {
        axis: usize,
    },
    /// Object `index`; for a box, `axis` is the axis of the face entered.
    Object {
        index: usize,
        axis: usize,
    },
}

/// The two coordinates of `point` along a plane perpendicular to `axis`, as a texture point.
fn plane_coordinates(point: Vec3, axis: usize) -> Vec3 {
    [point[(axis + 1) % 3], point[(axis + 2) % 3], 0.0]
}

/// A procedurally textured room (a box seen from inside: floor, ceiling and four walls)
/// containing a few axis-aligned boxes and spheres, each with a random procedural texture
/// (stripes, checkers or smooth value noise in random colours), so that camera motion
/// produces strong parallax and texture cues for pose learning.
#[derive(Debug, Clone)]
pub struct Scene {
    config: SceneConfig,
    /// Half extents of the room, which spans `[-half, half]` on each axis.
    half: Vec3,
    /// Room face textures, indexed `2 * axis + (1 for the face on the positive side)`.
    faces: [Texture; 6],
    objects: Vec<Object>,
}

impl Scene {
    /// A random scene, deterministic from `(seed, index)`, so datasets can be regenerated
    /// instead of stored. Rooms measure 6-9 m wide, 2.8-4 m high and 7-10 m deep; each object
    /// draws from its own stream, so changing `config.objects` keeps the others in place.
    pub fn random(seed: u64, index: u64, config: &SceneConfig) -> Self {
        let mut stream = Stream::new(&[seed, index, SCENE_TAG]);
        let half = [
            stream.uniform_in(3.0, 4.5),
            stream.uniform_in(1.4, 2.0),
            stream.uniform_in(3.5, 5.0),
        ];
        let faces = from_fn(|_| Texture::random(&mut stream, 0.4, 1.5));
        let objects = (0..config.objects as u64)
            .map(|object| {
                let mut object_stream = Stream::new(&[seed, index, OBJECT_TAG, object]);
                Object::random(&mut object_stream, half)
            })
            .collect();
        Self {
            config: config.clone(),
            half,
            faces,
            objects,
        }
    }

    /// Ray-casts one square pinhole image (`config.image_size` pixels a side, `config.fov_degrees`
    /// field of view, principal point at the image centre, one ray through each pixel
    /// centre) seen from `pose`: the image of a known pose that the training data is made of.
    ///
    /// Shading is texture colour times `0.3 + 0.7 * (0.5 + 0.5 * n·l)` for a fixed light
    /// direction `l` (wrapped Lambert, no shadows); colours in `[0, 1]` map to `[-1, 1]`.
    /// The camera is expected inside the room; rays that hit nothing are mid-grey.
    pub fn render(&self, pose: &CameraPose) -> Image {
        let size = self.config.image_size;
        let half_size = 0.5 * size as f64;
        let focal = half_size / (0.5 * self.config.fov_degrees.to_radians()).tan();
        let origin = pose.center();
        let mut pixels = Vec::with_capacity(size * size * 3);
        for row in 0..size {
            let y = (row as f64 + 0.5 - half_size) / focal;
            for column in 0..size {
                let x = (column as f64 + 0.5 - half_size) / focal;
                let direction = rotate_transposed(&pose.rotation, [x, y, 1.0]);
                let colour = self.trace(origin, direction);
                pixels.extend(colour.map(|v| (2.0 * v - 1.0).clamp(-1.0, 1.0) as f32));
            }
        }
        Image {
            height: size,
            width: size,
            pixels,
        }
    }

    /// Renders every pose of a trajectory, in order: one training sequence.
    pub fn render_trajectory(&self, trajectory: &Trajectory) -> Vec<Image> {
        trajectory
            .poses
            .iter()
            .map(|pose| self.render(pose))
            .collect()
    }

    /// The shaded colour in `[0, 1]` seen along a ray (`direction` need not be unit length).
    fn trace(&self, origin: Vec3, direction: Vec3) -> Vec3 {
        let inverse = direction.map(|v| 1.0 / v);
        let mut nearest = f64::INFINITY;
        let mut hit = Hit::Nothing;

        for axis in 0..3 {
            let wall = if direction[axis] > 0.0 {
                self.half[axis]
            } else {
                -self.half[axis]
            };
            let t = (wall - origin[axis]) * inverse[axis];
            if t > EPSILON && t < nearest {
                nearest = t;
                hit = Hit::Room { axis };
            }
        }

        for (index, object) in self.objects.iter().enumerate() {
            match object.shape {
                Shape::Cuboid { min, max } => {
                    let mut enter = f64::NEG_INFINITY;
                    let mut exit = f64::INFINITY;
                    let mut enter_axis = 0;
                    for axis in 0..3 {
                        let a = (min[axis] - origin[axis]) * inverse[axis];
                        let b = (max[axis] - origin[axis]) * inverse[axis];
                        let (near, far) = if a < b { (a, b) } else { (b, a) };
                        if near > enter {
                            enter = near;
                            enter_axis = axis;
                        }
                        exit = exit.min(far);
                    }
                    if enter <= exit && enter > EPSILON && enter < nearest {
                        nearest = enter;
                        hit = Hit::Object {
                            index,
                            axis: enter_axis,
                        };
                    }
                }
                Shape::Sphere { center, radius } => {
                    let offset = sub(origin, center);
                    let a = dot(direction, direction);
                    let b = dot(offset, direction);
                    let c = dot(offset, offset) - radius * radius;
                    let discriminant = b * b - a * c;
                    if discriminant >= 0.0 {
                        let t = (-b - discriminant.sqrt()) / a;
                        if t > EPSILON && t < nearest {
                            nearest = t;
                            hit = Hit::Object { index, axis: 0 };
                        }
                    }
                }
            }
        }

        let point = add_scaled(origin, direction, nearest);
        let (normal, texture, texture_point) = match hit {
            Hit::Nothing => return BACKGROUND,
            Hit::Room { axis } => {
                let mut normal = [0.0; 3];
                normal[axis] = -direction[axis].signum();
                let face = 2 * axis + usize::from(direction[axis] > 0.0);
                (normal, &self.faces[face], plane_coordinates(point, axis))
            }
            Hit::Object { index, axis } => {
                let object = &self.objects[index];
                match object.shape {
                    Shape::Cuboid { min, .. } => {
                        let mut normal = [0.0; 3];
                        normal[axis] = -direction[axis].signum();
                        let local = plane_coordinates(sub(point, min), axis);
                        (normal, &object.texture, local)
                    }
                    Shape::Sphere { center, radius } => {
                        let local = sub(point, center);
                        (local.map(|v| v / radius), &object.texture, local)
                    }
                }
            }
        };
        let shade = AMBIENT + DIFFUSE * (0.5 + 0.5 * dot(normal, LIGHT));
        texture.colour(texture_point).map(|c| c * shade)
    }
}

#[cfg(test)]
mod tests {
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
}
