//! The fly camera and the keys that move it, shared by the window and the browser page.
//!
//! Keys are named by their physical position as the W3C `KeyboardEvent.code` names them
//! ("KeyW", "ArrowUp", "Space"): the browser hands these names out, and winit's `KeyCode`
//! variants carry the same names, so one table serves both shells and a French keyboard flies
//! with the keys where WASD would be.

use brickcast_protocol::viewpoint;
use brickcast_protocol::wire::View;
use brickcast_protocol::{BrickMap, Camera};

/// Keys that fly forward/back, right/left, up/down: (positive, negative) per axis.
pub const MOVE_KEYS: [(&[&str], &[&str]); 3] = [
    (&["KeyW", "ArrowUp"], &["KeyS", "ArrowDown"]),
    (&["KeyD", "ArrowRight"], &["KeyA", "ArrowLeft"]),
    (&["Space", "KeyE"], &["KeyQ", "KeyC"]),
];

/// Movement asked for by the keys held now, as (forward, right, up), each -1, 0 or 1.
pub fn movement(held: impl Fn(&str) -> bool) -> [f32; 3] {
    MOVE_KEYS.map(|(plus, minus)| {
        let any = |ks: &[&str]| ks.iter().any(|k| held(k));
        f32::from(u8::from(any(plus))) - f32::from(u8::from(any(minus)))
    })
}

/// A free-flying camera: position plus yaw/pitch, y up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlyCamera {
    pub eye: [f32; 3],
    pub yaw: f32,
    pub pitch: f32,
    pub fov_y: f32,
    /// Voxels per second.
    pub speed: f32,
}

impl FlyCamera {
    /// Starts at `camera`, moving about an eighth of the scene per second.
    pub fn from_camera(camera: &Camera, size: [u32; 3]) -> FlyCamera {
        let d: [f32; 3] = std::array::from_fn(|i| camera.target[i] - camera.eye[i]);
        let flat = (d[0] * d[0] + d[2] * d[2]).sqrt();
        FlyCamera {
            eye: camera.eye,
            yaw: d[2].atan2(d[0]),
            pitch: d[1].atan2(flat),
            fov_y: camera.fov_y,
            speed: size.iter().copied().max().unwrap_or(64) as f32 / 8.0,
        }
    }

    pub fn forward(&self) -> [f32; 3] {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        [cp * cy, sp, cp * sy]
    }

    pub fn camera(&self) -> Camera {
        let f = self.forward();
        Camera {
            eye: self.eye,
            target: std::array::from_fn(|i| self.eye[i] + f[i]),
            fov_y: self.fov_y,
        }
    }

    /// Moves by `dir` (forward, right, up) for `dt` seconds.
    pub fn fly(&mut self, dir: [f32; 3], dt: f32) {
        let f = self.forward();
        let (sy, cy) = self.yaw.sin_cos();
        let right = [-sy, 0.0, cy];
        let step = self.speed * dt;
        for i in 0..3 {
            self.eye[i] += (f[i] * dir[0] + right[i] * dir[1] + [0.0, 1.0, 0.0][i] * dir[2]) * step;
        }
    }

    /// Puts the camera at `view`'s eye, looking where it looks (following someone).
    pub fn look_along(&mut self, view: View) {
        let f = view.forward;
        let flat = (f[0] * f[0] + f[2] * f[2]).sqrt();
        if view.is_valid() {
            self.eye = view.eye;
            self.yaw = f[2].atan2(f[0]);
            self.pitch = f[1].atan2(flat).clamp(-1.55, 1.55);
        }
    }

    pub fn look(&mut self, dx: f32, dy: f32) {
        const SENSITIVITY: f32 = 0.003;
        self.yaw += dx * SENSITIVITY;
        self.pitch = (self.pitch - dy * SENSITIVITY).clamp(-1.55, 1.55);
    }
}

/// Whether `map` holds a working set (stand-ins for coarse levels far away).
fn map_is_partial(map: &BrickMap) -> bool {
    map.stand_in_count() > 0
}

/// Field of view of a viewer's first camera, degrees.
pub const FIRST_FOV: f32 = 55.0;

/// Places a viewer's first camera, then improves it once. Why: at Welcome the map is still
/// empty, so the best a viewer can do is the grid's overview; once the scene has synced,
/// [`viewpoint::find`] can see the model and pick a camera that shows it (from inside, for an
/// enclosed one). The better view replaces the first only while the user has not moved it,
/// and never for a working set (a copy that holds only part of the scene, `Replica::held`): its
/// camera decides what it holds, so it stays where the user put it.
#[derive(Debug, Default)]
pub struct FirstView {
    placed: Option<FlyCamera>,
    settled: bool,
}

impl FirstView {
    /// Call every frame with the viewer's camera and its copy of the scene.
    pub fn place(&mut self, camera: &mut Option<FlyCamera>, map: &BrickMap, synced: bool) {
        let size = map.size();
        if camera.is_none() {
            let mut overview = Camera::overview(size);
            overview.fov_y = FIRST_FOV;
            let first = FlyCamera::from_camera(&overview, size);
            *camera = Some(first);
            self.placed = Some(first);
        }
        if synced && !self.settled && !map_is_partial(map) {
            self.settled = true;
            if *camera == self.placed {
                let found = viewpoint::find(map, FIRST_FOV).camera;
                *camera = Some(FlyCamera::from_camera(&found, size));
            }
        }
    }
}
