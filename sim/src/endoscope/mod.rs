//! # The simulated stereo endoscope (issue 16, the simulator's part)
//!
//! A CPU renderer of what a stereo endoscope on the endoscope-holder arm sees: a textured
//! tissue surface and one or two laparoscopic instruments, with ground truth for tool-line
//! detection, the dual RCM-arm calibration and stereo tool tracking. See `docs/vision.md`.
//!
//! - [`config`]: [`EndoscopeConfig`] (serde/TOML): cameras, timing, light, instrument,
//!   materials, tissue and the realism options, each switchable;
//! - [`mesh`]: the parametric instrument (shaft, wrist link, two jaws) as triangle meshes,
//!   OBJ written and read (`tobj`);
//! - [`tissue`]: the procedural tissue (height field and texture, precomputed once);
//! - [`raster`]: our z-buffered triangle rasteriser (perspective-correct);
//! - [`scene`]: the scene at one instant, and [`scene::DemoMotion`];
//! - [`render`]: [`StereoRenderer`], one [`StereoFrame`] per call;
//! - [`truth`]: the analytic ground truth (poses, tip, shaft contours and axis);
//! - [`output`]: PNG frames, masks, the ground truth as JSON Lines, sample images.
//!
//! Frames and units: the world is `{e}`, the endoscope arm's remote centre of motion
//! (`docs/calibration.md`); the left eye is the endoscope camera frame `{c}` (z forward, x
//! right, y down), the right eye is `{c}` moved by the baseline along `x`; metres, radians,
//! pixels with the centre of the top-left pixel at `(0, 0)`; times in nanoseconds on the
//! caller's clock (each frame carries its exposure's mid time).
#![warn(missing_docs)]

pub mod config;
pub mod mesh;
pub mod output;
pub mod raster;
pub mod render;
pub mod scene;
pub mod tissue;
pub mod truth;

pub use config::EndoscopeConfig;
pub use mesh::{InstrumentGeometry, InstrumentMesh, ObjError};
pub use render::{
    Eye, EyeImage, EyeTruth, NewRendererError, Occluder, RenderError, StereoFrame, StereoRenderer, Visibility,
    frame_mid_time_ns, label,
};
pub use scene::{DemoMotion, InstrumentState, SceneState};

#[cfg(test)]
mod tests;
