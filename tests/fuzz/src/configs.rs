//! fulcrumd's and simrobot's TOML configurations: a typed error or an accepted configuration
//! that builds what it configures; never a panic.

use std::path::Path;

use controller::config::Config;
use controller::cycle::{Acquisition, Estimation};
use sim::endoscope::EndoscopeConfig;
use sim::twin::TwinConfig;

/// `data` as fulcrumd's configuration (`Config::from_toml`, the daemon's own parser and
/// validation); an accepted configuration must build acquisition and estimation, and read back
/// the same from its own TOML.
pub fn fulcrumd_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(cfg) = Config::from_toml(text, Path::new("fuzz.toml")) else { return };
    let acq = Acquisition::new(&cfg.bus.encoder, cfg.health);
    assert!(acq.is_ok(), "accepted configuration, acquisition refuses it: {acq:?}");
    let est = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector);
    assert!(est.is_ok(), "accepted configuration, estimation refuses it: {:?}", est.err());
    if let Ok(again) = toml::to_string(&cfg) {
        let back = Config::from_toml(&again, Path::new("again.toml"));
        assert!(back.is_ok(), "an accepted configuration does not read back from its TOML: {back:?}\n{again}");
    }
}

/// `data` as simrobot's configuration (`--config`, a `TwinConfig`) and as its renderer's
/// (`--endoscope-config`, an `EndoscopeConfig`, validated as `simrobot` does).
pub fn simrobot_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(twin) = toml::from_str::<TwinConfig>(text)
        && let Ok(again) = toml::to_string(&twin)
    {
        let back = toml::from_str::<TwinConfig>(&again);
        assert!(back.is_ok(), "an accepted twin configuration does not read back: {back:?}\n{again}");
    }
    if let Ok(endoscope) = toml::from_str::<EndoscopeConfig>(text) {
        let _ = endoscope.validate();
    }
}
