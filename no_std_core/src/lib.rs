//! orbit-nerf-core: a K-Planes radiance field trained inside one caller-provided byte arena.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod camera;

pub use camera::{Camera, Pose};
pub use glam;
