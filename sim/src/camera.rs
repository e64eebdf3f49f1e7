//! The simulated stereo endoscope as a camera source ([`hw_io::camera::CameraSource`]): frames
//! rendered by [`crate::endoscope::StereoRenderer`] from a scene given as a function of time,
//! at the configured frame rate, each stamped with its exposure's mid time.
//!
//! Two timings ([`SimTiming`]): `Free` renders frame `n` at `t0 + n/fps` as fast as asked (an
//! offline sequence); `Clock` delivers frame `n` only once its exposure has ended on
//! `CLOCK_MONOTONIC`, as a real camera would, so that a scene fed live by the
//! simulated arms (`simrobot live --camera`) has the states the exposure needs. Frames the
//! renderer cannot keep up with are skipped (counted as dropped), so the timestamps stay on
//! the frame-rate grid.
//!
//! Units: nanoseconds of the caller's clock (`CLOCK_MONOTONIC` with `Clock`), pixels.

use std::time::Duration;

use hw_io::camera::{CameraSource, FrameFormat, Next, SourceCounters};
use hw_io::frame::{FormatError, FrameMeta, ImageLayout, PixelFormat, monotonic_now_ns};

use crate::endoscope::{RenderError, SceneState, StereoFrame, StereoRenderer, frame_mid_time_ns};

/// How the simulated camera's frames are timed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimTiming {
    /// Frame `n` at `t0 + n/fps`, rendered when asked.
    Free,
    /// Frame `n` at `t0 + n/fps` on `CLOCK_MONOTONIC`, delivered after its exposure ends; frames
    /// already past when the renderer is free again are skipped and counted as dropped.
    Clock,
}

/// Why the simulated camera could not deliver a frame.
#[derive(Debug, thiserror::Error)]
pub enum SimCameraError {
    /// The caller's buffer is not one stereo frame.
    #[error("buffer of {got} bytes, one stereo frame is {expected}")]
    Buffer {
        /// Bytes of one frame.
        expected: usize,
        /// The buffer's length.
        got: usize,
    },
    /// The scene is not renderable (a non-finite pose).
    #[error(transparent)]
    Render(#[from] RenderError),
    /// The renderer's image is not the configured size (a bug: never sent as a frame).
    #[error("rendered {got}-byte eye image, the frame format needs {expected}")]
    ImageSize {
        /// Bytes of one eye in the frame format.
        expected: usize,
        /// Bytes the renderer produced.
        got: usize,
    },
}

/// Why [`SimCamera::new`] failed.
#[derive(Debug, thiserror::Error)]
pub enum SimCameraConfigError {
    /// The configured image size is not a usable layout.
    #[error("camera image size: {0}")]
    Format(#[from] FormatError),
    /// The frame rate is not positive and finite.
    #[error("fps = {0}: must be positive and finite")]
    Fps(f64),
}

/// The simulated stereo endoscope as a [`CameraSource`]: 8-bit RGB, two eyes (left first).
pub struct SimCamera<F: Fn(u64) -> SceneState> {
    renderer: StereoRenderer,
    scene: F,
    frame: StereoFrame,
    format: FrameFormat,
    t0_ns: u64,
    fps: f64,
    exposure_ns: u32,
    timing: SimTiming,
    camera_id: u32,
    max_frames: Option<u64>,
    next: u64,
    counters: SourceCounters,
    ready: Option<ReadyFn>,
    uncovered: u64,
}

/// `ready(from_ns, to_ns)`: whether the scene is known over an exposure (see
/// [`SimCamera::with_ready`]).
type ReadyFn = Box<dyn Fn(u64, u64) -> bool + Send>;

/// How long past its exposure's end a `Clock` frame waits for [`SimCamera::with_ready`]'s
/// predicate before it is rendered with what the scene has (nanoseconds).
pub const MAX_READY_WAIT_NS: u64 = 100_000_000;

impl<F: Fn(u64) -> SceneState> core::fmt::Debug for SimCamera<F> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("SimCamera")
            .field("format", &self.format)
            .field("t0_ns", &self.t0_ns)
            .field("fps", &self.fps)
            .field("timing", &self.timing)
            .field("next", &self.next)
            .finish_non_exhaustive()
    }
}

impl<F: Fn(u64) -> SceneState> SimCamera<F> {
    /// A camera rendering `scene` with `renderer`; frame 0's mid-exposure time is `t0_ns`, the
    /// frame rate and exposure those of the renderer's configuration; at most `max_frames`.
    pub fn new(
        renderer: StereoRenderer,
        scene: F,
        t0_ns: u64,
        timing: SimTiming,
        camera_id: u32,
        max_frames: Option<u64>,
    ) -> Result<Self, SimCameraConfigError> {
        let cfg = renderer.config();
        let (w, h) = (cfg.camera.intrinsics.width, cfg.camera.intrinsics.height);
        let fps = cfg.timing.fps;
        if !(fps.is_finite() && fps > 0.0) {
            return Err(SimCameraConfigError::Fps(fps));
        }
        let exposure_ns = (cfg.timing.exposure_s * 1e9).round().clamp(0.0, f64::from(u32::MAX)) as u32;
        let layout = ImageLayout::packed(w, h, PixelFormat::Rgb8).map_err(FormatError::from)?;
        let format = FrameFormat::new(2, layout)?;
        Ok(Self {
            renderer,
            scene,
            frame: StereoFrame::default(),
            format,
            t0_ns,
            fps,
            exposure_ns,
            timing,
            camera_id,
            max_frames,
            next: 0,
            counters: SourceCounters::default(),
            ready: None,
            uncovered: 0,
        })
    }

    /// With `Clock` timing, also waits until `ready(exposure start, exposure end)` (nanoseconds)
    /// says the scene is known over the whole exposure (a live world has recorded the SYNCs
    /// that bracket it), at most [`MAX_READY_WAIT_NS`] past the exposure's end; after that the
    /// frame is rendered with what the scene gives and counted ([`uncovered`](Self::uncovered)).
    pub fn with_ready(mut self, ready: impl Fn(u64, u64) -> bool + Send + 'static) -> Self {
        self.ready = Some(Box::new(ready));
        self
    }

    /// Frames rendered before the scene covered their exposure (see [`with_ready`](Self::with_ready)).
    pub fn uncovered(&self) -> u64 {
        self.uncovered
    }

    /// The last frame rendered, with its ground truth (the frame [`CameraSource::next_into`]
    /// just delivered).
    pub fn last_frame(&self) -> &StereoFrame {
        &self.frame
    }
}

impl<F: Fn(u64) -> SceneState> CameraSource for SimCamera<F> {
    type Error = SimCameraError;

    fn format(&self) -> FrameFormat {
        self.format
    }

    fn next_into(&mut self, dst: &mut [u8], timeout: Duration) -> Result<Next, SimCameraError> {
        let expected = self.format.payload_bytes();
        if dst.len() != expected {
            return Err(SimCameraError::Buffer { expected, got: dst.len() });
        }
        if self.max_frames.is_some_and(|m| self.next >= m) {
            return Ok(Next::End);
        }
        let half_exposure = u64::from(self.exposure_ns / 2);
        if self.timing == SimTiming::Clock {
            let now = monotonic_now_ns();
            // Skip the frames whose exposure ended long ago (the renderer fell behind): a real
            // camera would have overwritten them.
            let period_ns = 1e9 / self.fps;
            loop {
                let end = frame_mid_time_ns(self.t0_ns, self.fps, self.next) + half_exposure;
                if now <= end + period_ns as u64 || self.max_frames.is_some_and(|m| self.next + 1 >= m) {
                    break;
                }
                self.next += 1;
                self.counters.dropped += 1;
            }
            let mid = frame_mid_time_ns(self.t0_ns, self.fps, self.next);
            let end = mid + half_exposure;
            if end > now {
                let wait = Duration::from_nanos(end - now);
                if wait > timeout {
                    std::thread::sleep(timeout);
                    return Ok(Next::Timeout);
                }
                std::thread::sleep(wait);
            }
            if let Some(ready) = &self.ready {
                let start = mid.saturating_sub(half_exposure);
                let waited_from = monotonic_now_ns();
                loop {
                    if ready(start, end) {
                        break;
                    }
                    let now = monotonic_now_ns();
                    if now >= end + MAX_READY_WAIT_NS {
                        self.uncovered += 1;
                        break;
                    }
                    if Duration::from_nanos(now - waited_from) >= timeout {
                        return Ok(Next::Timeout);
                    }
                    std::thread::sleep(Duration::from_millis(1));
                }
            }
        }
        let n = self.next;
        let t_mid_ns = frame_mid_time_ns(self.t0_ns, self.fps, n);
        self.next += 1;
        if let Err(e) = self.renderer.render_into(t_mid_ns, &self.scene, &mut self.frame) {
            self.counters.dropped += 1;
            return Err(e.into());
        }
        let eye_bytes = self.format.layout.eye_bytes();
        for (eye, img) in self.frame.images.iter().enumerate() {
            if img.rgb.len() != eye_bytes {
                self.counters.dropped += 1;
                return Err(SimCameraError::ImageSize { expected: eye_bytes, got: img.rgb.len() });
            }
            dst[eye * eye_bytes..(eye + 1) * eye_bytes].copy_from_slice(&img.rgb);
        }
        self.counters.delivered += 1;
        Ok(Next::Frame(FrameMeta {
            sequence: n,
            camera_id: self.camera_id,
            timestamp_ns: t_mid_ns,
            exposure_ns: self.exposure_ns,
            eyes: 2,
            layout: self.format.layout,
        }))
    }

    fn counters(&self) -> SourceCounters {
        self.counters
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use crate::endoscope::{DemoMotion, EndoscopeConfig};

    fn small_config() -> EndoscopeConfig {
        let mut cfg = EndoscopeConfig::default();
        cfg.camera.intrinsics.width = 160;
        cfg.camera.intrinsics.height = 120;
        cfg.camera.intrinsics.fx = 100.0;
        cfg.camera.intrinsics.fy = 100.0;
        cfg.camera.intrinsics.cx = 79.5;
        cfg.camera.intrinsics.cy = 59.5;
        cfg
    }

    #[test]
    fn free_timing_delivers_the_renderers_images_on_the_frame_grid() {
        let cfg = small_config();
        let renderer = StereoRenderer::new(cfg.clone(), cfg.instrument.mesh().unwrap()).unwrap();
        let motion = DemoMotion::default();
        let mut cam =
            SimCamera::new(renderer, |t| motion.state_at(t), 1_000_000_000, SimTiming::Free, 7, Some(3)).unwrap();
        let f = cam.format();
        assert_eq!((f.eyes, f.layout.width, f.layout.height, f.layout.format), (2, 160, 120, PixelFormat::Rgb8));
        let mut buf = vec![0u8; f.payload_bytes()];
        let mut reference = StereoRenderer::new(cfg.clone(), cfg.instrument.mesh().unwrap()).unwrap();
        for n in 0..3 {
            let Next::Frame(m) = cam.next_into(&mut buf, Duration::ZERO).unwrap() else { panic!() };
            let t = frame_mid_time_ns(1_000_000_000, cfg.timing.fps, n);
            assert_eq!((m.sequence, m.timestamp_ns, m.camera_id), (n, t, 7));
            let expected = reference.render(t, &|t| motion.state_at(t)).unwrap();
            assert_eq!(&buf[..buf.len() / 2], &expected.images[0].rgb[..]);
            assert_eq!(&buf[buf.len() / 2..], &expected.images[1].rgb[..]);
            assert_eq!(cam.last_frame().t_mid_ns, t);
        }
        assert_eq!(cam.next_into(&mut buf, Duration::ZERO).unwrap(), Next::End);
        assert!(matches!(cam.next_into(&mut [0u8; 1], Duration::ZERO), Err(SimCameraError::Buffer { .. })));
    }

    #[test]
    fn clock_timing_waits_for_the_exposure_and_skips_frames_long_past() {
        let cfg = small_config();
        let renderer = StereoRenderer::new(cfg.clone(), cfg.instrument.mesh().unwrap()).unwrap();
        let motion = DemoMotion::default();
        // Frame 0 was 1 s ago: about 30 frames are long past and skipped.
        let t0 = monotonic_now_ns() - 1_000_000_000;
        let mut cam = SimCamera::new(renderer, |t| motion.state_at(t), t0, SimTiming::Clock, 0, None).unwrap();
        let mut buf = vec![0u8; cam.format().payload_bytes()];
        let Next::Frame(m) = cam.next_into(&mut buf, Duration::from_secs(1)).unwrap() else { panic!() };
        assert!(m.sequence >= 28, "{m:?}");
        assert_eq!(cam.counters().dropped, m.sequence);
        let half = u64::from(m.exposure_ns / 2);
        assert!(monotonic_now_ns() >= m.timestamp_ns + half, "delivered after its exposure ended");
        // The next one is in the future: delivered only after its exposure, on the grid.
        let Next::Frame(m2) = cam.next_into(&mut buf, Duration::from_secs(1)).unwrap() else { panic!() };
        assert_eq!(m2.sequence, m.sequence + 1);
        assert!(monotonic_now_ns() >= m2.timestamp_ns + half);
        assert_eq!(m2.timestamp_ns, frame_mid_time_ns(t0, cfg.timing.fps, m2.sequence));
    }
}
