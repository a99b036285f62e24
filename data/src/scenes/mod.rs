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

use crate::frame::Image;
use crate::rng::Stream;

/// A point or direction in world or camera space.
type Vec3 = [f64; 3];

mod texture;

use texture::Texture;

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
        Self::random_between_frames(seed, index, frames, 1)
    }

    /// The path [`Trajectory::random`] draws for `(seed, index, frames)`, sampled at
    /// `subdivisions` evenly spaced poses per gap between its frames: every `subdivisions`-th
    /// pose is one of its frames, the others lie between them on the same motion.
    pub fn random_between_frames(
        seed: u64,
        index: u64,
        frames: usize,
        subdivisions: usize,
    ) -> Self {
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

        let subdivisions = subdivisions.max(1);
        let samples = match frames {
            0 => 0,
            _ => (frames - 1) * subdivisions + 1,
        };
        let sample_spans = spans * subdivisions as f64;
        let poses = (0..samples)
            .map(|sample| {
                let u = if sample_spans > 0.0 {
                    sample as f64 / sample_spans
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
        let (nearest, hit) = self.nearest_hit(origin, direction);
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

    /// The ray parameter of the first surface a ray hits (infinite if none), and that surface.
    fn nearest_hit(&self, origin: Vec3, direction: Vec3) -> (f64, Hit) {
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
        (nearest, hit)
    }
}

#[cfg(test)]
mod tests;
