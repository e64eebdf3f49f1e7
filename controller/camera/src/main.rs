//! `comanip-camera`: publish a camera source on the frame service, or watch the frame service
//! (`docs/frames.md`).
//!
//! Exit codes: 0 success; 1 run-time error; 2 bad command line; 3 the source cannot be opened;
//! 4 (`monitor --expect-in-order`) frames were lost, refused or out of order.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::{Parser, Subcommand};
use comanip_camera::{Monitor, pump};
use controller::process::{STOP, init_logging, install_stop_handlers, write_json};
use hw_io::camera::CameraSource;
use hw_io::camera::image_sequence::{ImageSequence, ImageSequenceConfig, Timing};
use hw_io::camera::v4l2::{CaptureFormat, Stereo, V4l2Config, V4l2Source};
use hw_io::frame::{PixelFormat, monotonic_now_ns};
use hw_io::ipc::{DEFAULT_FRAME_SERVICE, FramePublisher, FrameSubscriber, PublisherOptions, ReceivedFrame};
use std::sync::atomic::Ordering;
use tracing::{error, info, warn};

#[derive(Parser)]
#[command(name = "comanip-camera", version, about = "Camera sources into the frame service, and a frame monitor")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Publish the frames of an image-sequence directory (PNG images and frames.txt).
    Images {
        /// The directory (its frames.txt lists `t_mid_ns exposure_ns left.png [right.png]`).
        dir: PathBuf,
        /// Play at the recorded intervals, stamped on this machine's CLOCK_MONOTONIC (default:
        /// the recorded timestamps, as fast as subscribers are served).
        #[arg(long)]
        paced: bool,
        /// Start again after the last frame.
        #[arg(long)]
        repeat: bool,
        /// Camera rig id in the frame headers.
        #[arg(long, default_value_t = 0)]
        camera_id: u32,
        /// Frame service name.
        #[arg(long, default_value = DEFAULT_FRAME_SERVICE)]
        service: String,
        /// Stop after this many frames.
        #[arg(long)]
        frames: Option<u64>,
        /// Write the run's summary here (JSON).
        #[arg(long)]
        summary_json: Option<PathBuf>,
    },
    /// Publish a Video4Linux2 capture device (a frame grabber, a USB endoscope; docs/camera.md).
    V4l2 {
        /// The device.
        #[arg(long, default_value = "/dev/video0")]
        device: PathBuf,
        /// Pixel format asked of the device (MJPEG is decoded to RGB).
        #[arg(long, value_enum, default_value = "yuyv")]
        format: V4l2Format,
        /// Width of the captured frame, pixels (both eyes with --side-by-side).
        #[arg(long, default_value_t = 640)]
        width: u32,
        /// Height, pixels.
        #[arg(long, default_value_t = 480)]
        height: u32,
        /// Frame rate asked of the device, Hz (0: the device's).
        #[arg(long, default_value_t = 0)]
        fps: u32,
        /// The device delivers a stereo pair side by side (left half, right half).
        #[arg(long)]
        side_by_side: bool,
        /// Exposure time, microseconds, when known (for the mid-exposure timestamp).
        #[arg(long)]
        exposure_us: Option<u32>,
        /// Camera rig id in the frame headers.
        #[arg(long, default_value_t = 0)]
        camera_id: u32,
        /// Frame service name.
        #[arg(long, default_value = DEFAULT_FRAME_SERVICE)]
        service: String,
        /// Stop after this many frames.
        #[arg(long)]
        frames: Option<u64>,
        /// Write the run's summary here (JSON).
        #[arg(long)]
        summary_json: Option<PathBuf>,
    },
    /// Subscribe to the frame service and report every frame: order, losses, timestamps, age.
    Monitor {
        /// Frame service name.
        #[arg(long, default_value = DEFAULT_FRAME_SERVICE)]
        service: String,
        /// Stop after this many frames.
        #[arg(long)]
        frames: Option<u64>,
        /// Stop when no frame arrived for this long, seconds (after the first frame; before it,
        /// wait up to `--start-timeout-s`).
        #[arg(long, default_value_t = 5.0)]
        idle_timeout_s: f64,
        /// How long to wait for the first frame, seconds.
        #[arg(long, default_value_t = 30.0)]
        start_timeout_s: f64,
        /// Print one line per frame (default: one line per second).
        #[arg(long)]
        every_frame: bool,
        /// Save each received frame's eyes as PNG into this directory (RGB and grey frames).
        #[arg(long)]
        save: Option<PathBuf>,
        /// Exit with code 4 unless every frame arrived, in order, with increasing timestamps and
        /// nothing refused.
        #[arg(long)]
        expect_in_order: bool,
        /// Write the summary here (JSON).
        #[arg(long)]
        summary_json: Option<PathBuf>,
    },
}

/// `--format` of `v4l2`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum V4l2Format {
    /// YUYV 4:2:2, delivered as is.
    Yuyv,
    /// RGB24, delivered as is.
    Rgb24,
    /// 8-bit grey, delivered as is.
    Grey,
    /// Motion JPEG, decoded to RGB.
    Mjpeg,
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() { ExitCode::from(2) } else { ExitCode::SUCCESS };
        }
    };
    init_logging();
    install_stop_handlers();
    match cli.command {
        Command::Images { dir, paced, repeat, camera_id, service, frames, summary_json } => {
            let mut cfg = ImageSequenceConfig::new(dir);
            cfg.timing = if paced { Timing::Paced } else { Timing::Recorded };
            cfg.repeat = repeat;
            cfg.camera_id = camera_id;
            match ImageSequence::open(cfg) {
                Ok(mut source) => run_source(&mut source, camera_id, &service, frames, summary_json),
                Err(e) => cannot_open(&e),
            }
        }
        Command::V4l2 {
            device,
            format,
            width,
            height,
            fps,
            side_by_side,
            exposure_us,
            camera_id,
            service,
            frames,
            summary_json,
        } => {
            let config = V4l2Config {
                device,
                format: match format {
                    V4l2Format::Yuyv => CaptureFormat::Yuyv,
                    V4l2Format::Rgb24 => CaptureFormat::Rgb24,
                    V4l2Format::Grey => CaptureFormat::Grey,
                    V4l2Format::Mjpeg => CaptureFormat::Mjpeg,
                },
                width_px: width,
                height_px: height,
                frame_rate_hz: fps,
                stereo: if side_by_side { Stereo::SideBySide } else { Stereo::Mono },
                camera_id,
                exposure_ns: exposure_us.map(|us| us.saturating_mul(1000)),
                ..V4l2Config::default()
            };
            match V4l2Source::open(&config) {
                Ok(mut source) => run_source(&mut source, camera_id, &service, frames, summary_json),
                Err(e) => cannot_open(&e),
            }
        }
        Command::Monitor {
            service,
            frames,
            idle_timeout_s,
            start_timeout_s,
            every_frame,
            save,
            expect_in_order,
            summary_json,
        } => monitor(MonitorArgs {
            service,
            frames,
            idle_timeout: secs(idle_timeout_s),
            start_timeout: secs(start_timeout_s),
            every_frame,
            save,
            expect_in_order,
            summary_json,
        }),
    }
}

/// A source that cannot be opened: logged, exit code 3.
fn cannot_open(e: &dyn std::error::Error) -> ExitCode {
    error!("{e}");
    ExitCode::from(3)
}

fn secs(s: f64) -> Duration {
    Duration::try_from_secs_f64(s.max(0.0)).unwrap_or(Duration::MAX)
}

fn run_source<S: CameraSource>(
    source: &mut S,
    camera_id: u32,
    service: &str,
    frames: Option<u64>,
    summary_json: Option<PathBuf>,
) -> ExitCode {
    let mut publisher = match FramePublisher::create(service, source.format(), camera_id, &PublisherOptions::frames()) {
        Ok(p) => p,
        Err(e) => {
            error!("cannot publish on {service}: {e}");
            return ExitCode::FAILURE;
        }
    };
    let f = source.format();
    info!(
        "publishing {}×{} {} ×{} frames on {service} (run {:016x})",
        f.layout.width,
        f.layout.height,
        f.layout.format,
        f.eyes,
        publisher.run_id()
    );
    let result = pump(source, &mut publisher, frames, &STOP);
    match result {
        Ok(summary) => {
            info!(
                "published {} frames; source delivered {}, dropped {}, errors {}; publish errors {}",
                summary.published,
                summary.source_delivered,
                summary.source_dropped,
                summary.source_errors,
                summary.publish_errors
            );
            if let Err(e) = write_json(summary_json.as_deref(), &summary) {
                error!("{e}");
                return ExitCode::FAILURE;
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            error!("{e}");
            ExitCode::FAILURE
        }
    }
}

struct MonitorArgs {
    service: String,
    frames: Option<u64>,
    idle_timeout: Duration,
    start_timeout: Duration,
    every_frame: bool,
    save: Option<PathBuf>,
    expect_in_order: bool,
    summary_json: Option<PathBuf>,
}

fn monitor(a: MonitorArgs) -> ExitCode {
    let mut sub = match FrameSubscriber::connect(&a.service, &PublisherOptions::frames()) {
        Ok(s) => s,
        Err(e) => {
            error!("cannot subscribe to {}: {e}", a.service);
            return ExitCode::FAILURE;
        }
    };
    println!("subscribed to {}", a.service);
    if let Some(dir) = &a.save
        && let Err(e) = std::fs::create_dir_all(dir)
    {
        error!("cannot create {}: {e}", dir.display());
        return ExitCode::FAILURE;
    }
    let mut mon = Monitor::default();
    let mut last_frame = Instant::now();
    let mut last_print = Instant::now();
    let mut got_any = false;
    while !STOP.load(Ordering::Relaxed) && a.frames.is_none_or(|n| sub.counters().received < n) {
        let limit = if got_any { a.idle_timeout } else { a.start_timeout };
        if last_frame.elapsed() >= limit {
            info!("no frame for {:.1} s: stopping", limit.as_secs_f64());
            break;
        }
        match sub.wait(Duration::from_millis(100)) {
            Ok(Some(frame)) => {
                got_any = true;
                last_frame = Instant::now();
                let age_ms = mon.record(&frame, monotonic_now_ns());
                let m = frame.meta();
                if a.every_frame || last_print.elapsed() >= Duration::from_secs(1) {
                    last_print = Instant::now();
                    println!(
                        "frame {:>6}  t_mid {} ns  {}×{} {} ×{}  age {age_ms:.1} ms  {:?}",
                        m.sequence,
                        m.timestamp_ns,
                        m.layout.width,
                        m.layout.height,
                        m.layout.format,
                        m.eyes,
                        frame.event
                    );
                }
                if let Some(dir) = &a.save {
                    save(&frame, dir);
                }
            }
            Ok(None) => {}
            Err(e) => warn!("{e}"),
        }
    }
    let summary = mon.summary(sub.counters());
    println!(
        "received {}, missed {}, restarts {}, rejected {}, source dropped {}, timestamps not increasing {}, median age {} ms",
        summary.received,
        summary.missed,
        summary.restarts,
        summary.rejected,
        summary.source_dropped,
        summary.timestamps_not_increasing,
        summary.median_age_ms.map_or("-".into(), |a| format!("{a:.1}"))
    );
    if let Err(e) = write_json(a.summary_json.as_deref(), &summary) {
        error!("{e}");
        return ExitCode::FAILURE;
    }
    let clean = summary.received > 0
        && summary.missed == 0
        && summary.rejected == 0
        && summary.restarts == 0
        && summary.timestamps_not_increasing == 0
        && summary.source_dropped == 0;
    if a.expect_in_order && !clean { ExitCode::from(4) } else { ExitCode::SUCCESS }
}

/// Saves each eye of `frame` as `DIR/frame_<seq>_<eye>.png` (RGB and grey frames; YUYV is
/// skipped with a warning).
fn save(frame: &ReceivedFrame, dir: &std::path::Path) {
    let m = frame.meta();
    let color = match m.layout.format {
        PixelFormat::Rgb8 => image::ExtendedColorType::Rgb8,
        PixelFormat::Gray8 => image::ExtendedColorType::L8,
        PixelFormat::Yuyv => {
            warn!("frame {}: YUYV frames are not saved", m.sequence);
            return;
        }
    };
    for eye in 0..m.eyes {
        let Some(bytes) = frame.eye(eye) else { continue };
        let row = m.layout.row_bytes();
        let packed: Vec<u8> =
            bytes.chunks(m.layout.stride as usize).flat_map(|r| r.get(..row).unwrap_or(r).iter().copied()).collect();
        let name = if m.eyes == 2 { ["left", "right"][eye as usize] } else { "mono" };
        let path = dir.join(format!("frame_{:06}_{name}.png", m.sequence));
        if let Err(e) = image::save_buffer(&path, &packed, m.layout.width, m.layout.height, color) {
            warn!("cannot save {}: {e}", path.display());
        }
    }
}
