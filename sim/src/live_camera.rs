//! The simulated stereo endoscope, live: frames of the two simulated arms rendered in step with
//! the live bus and published on the frame service (`simrobot live --camera`,
//! `docs/frames.md`).
//!
//! The SYNC loop records each answered SYNC into a shared [`World`] at its `CLOCK_MONOTONIC`
//! time (the kernel's receive timestamp of the SYNC, moved from `CLOCK_REALTIME` by
//! [`hw_io::frame::realtime_minus_monotonic_ns`]); a camera thread of lower priority renders
//! frame `n` (mid-exposure time `t0 + n/fps` on `CLOCK_MONOTONIC`) once its exposure has ended,
//! from the world's scene at the motion-blur instants, and publishes it with
//! [`hw_io::camera::pump`]. Frames the renderer cannot keep up with are skipped and counted
//! (`source_dropped` in every frame header). Until the first SYNC there is no world to film:
//! the camera waits for it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use hw_io::camera::{PumpError, PumpSummary, pump};
use hw_io::frame::monotonic_now_ns;
use hw_io::ipc::{FrameCreateError, FramePublisher, PublisherOptions};

use crate::camera::{SimCamera, SimCameraConfigError, SimTiming};
use crate::endoscope::{EndoscopeConfig, InstrumentMesh, NewRendererError, StereoRenderer};
use crate::world::World;

/// The world shared between the SYNC loop (writer) and the camera thread (reader).
pub type SharedWorld = Arc<Mutex<World>>;

/// Locks the world; a panicked holder leaves the data as it was (each record is one push).
pub fn lock(world: &SharedWorld) -> MutexGuard<'_, World> {
    world.lock().unwrap_or_else(PoisonError::into_inner)
}

/// What the live camera did (`simrobot live --summary-json`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CameraCounts {
    /// Frames sent on the frame service.
    pub published: u64,
    /// Frames rendered.
    pub rendered: u64,
    /// Frames skipped because the renderer was late (their exposure had long ended).
    pub skipped: u64,
    /// Frames lost to rendering or publishing errors.
    pub errors: u64,
    /// Frames rendered before the world had recorded the SYNCs around their whole exposure
    /// (the controller stopped sending SYNCs, or fell more than 100 ms behind): the arms are
    /// drawn as they were last recorded.
    pub uncovered: u64,
}

/// Settings of the live camera.
#[derive(Clone, Debug)]
pub struct LiveCameraConfig {
    /// The renderer's configuration (size, frame rate, exposure, realism).
    pub endoscope: EndoscopeConfig,
    /// The instrument mesh.
    pub mesh: InstrumentMesh,
    /// Frame service name.
    pub service: String,
    /// Camera rig id in the headers.
    pub camera_id: u32,
}

/// Why the live camera could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum LiveCameraError {
    /// The renderer's configuration.
    #[error("endoscope renderer: {0}")]
    Renderer(#[from] NewRendererError),
    /// The camera's frame format or rate.
    #[error(transparent)]
    Camera(#[from] SimCameraConfigError),
    /// The frame service.
    #[error("frame service: {0}")]
    Service(#[from] FrameCreateError),
    /// Publishing failed for good.
    #[error(transparent)]
    Pump(#[from] PumpError),
    /// The camera thread could not be started.
    #[error("cannot start the camera thread: {0}")]
    Thread(#[source] std::io::Error),
    /// The camera thread panicked (a bug).
    #[error("the camera thread panicked")]
    Panicked,
}

/// The running camera thread.
#[derive(Debug)]
pub struct LiveCamera {
    stop: Arc<AtomicBool>,
    handle: JoinHandle<Result<CameraCounts, LiveCameraError>>,
}

impl LiveCamera {
    /// Builds the renderer (the tissue texture is precomputed here, on the caller's thread,
    /// before the bus starts) and starts the camera thread on `world`; it returns when
    /// [`stop`](Self::stop) is called. Errors of the frame service come back from `stop`.
    pub fn spawn(world: SharedWorld, config: LiveCameraConfig) -> Result<Self, LiveCameraError> {
        let renderer = StereoRenderer::new(config.endoscope.clone(), config.mesh.clone())?;
        let stop = Arc::new(AtomicBool::new(false));
        let thread_stop = Arc::clone(&stop);
        let handle = std::thread::Builder::new()
            .name("simrobot-camera".into())
            .spawn(move || run(&world, renderer, config, &thread_stop))
            .map_err(LiveCameraError::Thread)?;
        Ok(Self { stop, handle })
    }

    /// Stops the thread and returns what it published.
    pub fn stop(self) -> Result<CameraCounts, LiveCameraError> {
        self.stop.store(true, Ordering::Relaxed);
        self.handle.join().map_err(|_| LiveCameraError::Panicked)?
    }
}

/// Puts the calling thread under the normal time-sharing policy with nice 10, whatever the
/// process runs at: `simrobot live` answers SYNCs at a real-time priority (the encoder nodes are
/// hardware of their own on a robot), and a camera thread inheriting it would take the CPU from
/// the controller's loop for each frame it renders. Returns false if the kernel refused.
pub fn lower_thread_priority() -> bool {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: sched_setscheduler(0, ...) acts on the calling thread; `param` is a valid
    // sched_param; SCHED_OTHER with priority 0 is always allowed (lowering needs no privilege).
    let policy_ok = unsafe { libc::sched_setscheduler(0, libc::SCHED_OTHER, &param) } == 0;
    // SAFETY: setpriority on the calling thread (its tid); raising the nice value needs no
    // privilege.
    let nice_ok = unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, 10) } == 0;
    policy_ok && nice_ok
}

fn run(
    world: &SharedWorld,
    renderer: StereoRenderer,
    config: LiveCameraConfig,
    stop: &AtomicBool,
) -> Result<CameraCounts, LiveCameraError> {
    if !lower_thread_priority() {
        tracing::warn!("the camera thread could not lower its scheduling priority");
    }
    let half_exposure_ns = (config.endoscope.timing.exposure_s * 0.5e9).max(0.0) as u64;
    // Wait for the first SYNC: there is no scene before it.
    let first = loop {
        if stop.load(Ordering::Relaxed) {
            return Ok(CameraCounts::default());
        }
        if let Some(s) = lock(world).history().next().map(|s| s.t_ns) {
            break s;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    // The first frame's exposure starts after the first recorded SYNC.
    let t0_ns = first.max(monotonic_now_ns()) + half_exposure_ns;
    // The world keeps at least its newest sample, so it has a scene from now on.
    let Some(fallback) = lock(world).scene_at(first) else {
        return Ok(CameraCounts::default());
    };
    let scene = move |t: u64| lock(world).scene_at(t).unwrap_or(fallback);
    let covered = Arc::clone(world);
    let mut camera = SimCamera::new(renderer, scene, t0_ns, SimTiming::Clock, config.camera_id, None)?
        .with_ready(move |from, to| lock(&covered).covers(from, to));
    let mut publisher = FramePublisher::create(
        &config.service,
        hw_io::camera::CameraSource::format(&camera),
        config.camera_id,
        &PublisherOptions::frames(),
    )?;
    let p: PumpSummary = pump(&mut camera, &mut publisher, None, stop)?;
    Ok(CameraCounts {
        published: p.published,
        rendered: p.source_delivered,
        skipped: p.source_dropped,
        errors: p.source_errors + p.publish_errors,
        uncovered: camera.uncovered(),
    })
}
