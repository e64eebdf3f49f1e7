//! iceoryx2's own log messages, through the application's `tracing` subscriber.
//!
//! iceoryx2 prints to the console with its own logger by default; a daemon's log must be one
//! stream (journald under systemd). [`route_iceoryx2_logs_to_tracing`] installs a logger that
//! forwards every iceoryx2 message to `tracing` under the target `iceoryx2`, at the same level,
//! except the start-up notice that no iceoryx2 config file was loaded: comanip configures its
//! services in code (`[output]` of its own config), so that notice is expected and goes to
//! `debug`.

use iceoryx2_log::{Log, LogLevel};

/// The forwarding logger.
struct TracingLog;

/// The notice iceoryx2 gives when it runs on its built-in defaults.
const NO_CONFIG_NOTICE: &str = "No config file was loaded";

impl Log for TracingLog {
    fn log(&self, level: LogLevel, origin: core::fmt::Arguments, message: core::fmt::Arguments) {
        let text = message.to_string();
        if text.contains(NO_CONFIG_NOTICE) {
            tracing::debug!(target: "iceoryx2", "{origin}: {text} (comanip configures its services itself)");
            return;
        }
        match level {
            LogLevel::Trace => tracing::trace!(target: "iceoryx2", "{origin}: {text}"),
            LogLevel::Debug => tracing::debug!(target: "iceoryx2", "{origin}: {text}"),
            LogLevel::Info => tracing::info!(target: "iceoryx2", "{origin}: {text}"),
            LogLevel::Warn => tracing::warn!(target: "iceoryx2", "{origin}: {text}"),
            LogLevel::Error | LogLevel::Fatal => tracing::error!(target: "iceoryx2", "{origin}: {text}"),
        }
    }
}

static LOGGER: TracingLog = TracingLog;

/// Routes iceoryx2's log messages to `tracing` (see the module doc). Call once at start-up,
/// before the first iceoryx2 node is created; returns false when iceoryx2 already had a
/// logger (it keeps that one). Not for the real-time loop.
pub fn route_iceoryx2_logs_to_tracing() -> bool {
    iceoryx2_log::set_logger(&LOGGER)
}
