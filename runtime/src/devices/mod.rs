//! Devices that run a scene's kernels besides the host backends of [`crate::engine`]:
//! [`gpu`], wgpu on any GPU (or Mesa's lavapipe).

pub mod gpu;
