//! One frame of a scene, ready for the sensors: the LiDAR ([`super::lidar`]) and the camera
//! ([`super::camera`]) render from it.

use glam::Affine3A;

use super::appearance::Appearance;
use super::config::LightingConfig;
use super::raycast::Accel;

/// One frame of a scene: the world at one instant with its ray-casting accelerator and the pose of
/// the LiDAR.
#[derive(Debug)]
pub struct SceneSnapshot {
    /// Ray-casting accelerator over every triangle at this instant.
    pub accel: Accel,
    /// Time since frame 0, seconds.
    pub time_s: f32,
    /// Pose of the LiDAR (world from LiDAR frame) at this instant.
    pub world_from_lidar: Affine3A,
    /// Lighting of the scene: the configured one, or the sun and sky drawn for the scene when its
    /// appearance is randomised ([`crate::sim::AppearanceConfig`]).
    pub lighting: LightingConfig,
    /// Cloud cover of the drawn sky in `[0, 1]` (0 for the configured lighting): clouds hide the
    /// sun's disc.
    pub overcast: f32,
    /// Random stream of this frame (ray drop, range noise).
    pub noise_seed: u64,
    /// The scene's drawn appearance (palettes, textures) when randomised; `None` renders the stock
    /// materials flat.
    pub(crate) appearance: Option<Appearance>,
}
