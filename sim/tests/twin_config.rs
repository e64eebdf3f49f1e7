//! `configs/simrobot.toml` lists exactly the defaults of `TwinConfig`, and config files are
//! checked strictly.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use hw_io::can::NmtState;
use sim::twin::{SimRobot, TwinConfig};

fn example() -> String {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/simrobot.toml");
    std::fs::read_to_string(path).unwrap()
}

#[test]
fn the_example_config_parses_and_equals_the_defaults() {
    let parsed: TwinConfig = toml::from_str(&example()).unwrap();
    assert_eq!(parsed, TwinConfig::default());
    assert!(SimRobot::new(&parsed).is_ok());
}

#[test]
fn an_empty_config_is_the_default_and_a_partial_one_overrides_only_its_keys() {
    assert_eq!(toml::from_str::<TwinConfig>("").unwrap(), TwinConfig::default());
    let c: TwinConfig = toml::from_str(
        "endless = true\n[scenario]\ncycles = 3\n[model_error]\nlink_length_m = 0.0\n\
         [[nodes]]\n[[nodes]]\nnmt = \"pre-operational\"\n[[nodes]]\n",
    )
    .unwrap();
    let mut expected = TwinConfig { endless: true, ..TwinConfig::default() };
    expected.scenario.cycles = 3;
    expected.model_error.link_length_m = 0.0;
    expected.nodes[1].nmt = NmtState::PreOperational;
    assert_eq!(c, expected);
}

#[test]
fn unknown_keys_and_wrong_node_counts_are_refused() {
    let err = toml::from_str::<TwinConfig>("[scenario]\ncycels = 3\n").unwrap_err();
    assert!(err.to_string().contains("cycels"), "{err}");
    let err = toml::from_str::<TwinConfig>("[model_error]\nlink_length = 0.1\n").unwrap_err();
    assert!(err.to_string().contains("link_length"), "{err}");
    assert!(toml::from_str::<TwinConfig>("[[nodes]]\nlatency_us = 5\n").is_err());
    assert!(toml::from_str::<TwinConfig>("[[nodes]]\n[[nodes]]\n[[nodes]]\nnmt = \"running\"\n").is_err());
    // Unknown keys inside a node table or an injected fault are named.
    let err = toml::from_str::<TwinConfig>("[[nodes]]\nlatencyus = 5\n[[nodes]]\n[[nodes]]\n").unwrap_err();
    assert!(err.to_string().contains("latencyus"), "{err}");
    let bad_emcy = "[[nodes]]\nemcy = [{ at_us = 1, duration_us = 2, code = 1, colour = 3 }]\n[[nodes]]\n[[nodes]]\n";
    let err = toml::from_str::<TwinConfig>(bad_emcy).unwrap_err();
    assert!(err.to_string().contains("colour"), "{err}");
    // A fault's register and vendor bytes are optional.
    let emcy = "[[nodes]]\nemcy = [{ at_us = 1, duration_us = 2, code = 0x7305 }]\n[[nodes]]\n[[nodes]]\n";
    let c = toml::from_str::<TwinConfig>(emcy).unwrap();
    assert_eq!((c.nodes[0].emcy[0].code, c.nodes[0].emcy[0].register, c.nodes[0].emcy[0].vendor), (0x7305, 0, [0; 5]));
}

#[test]
fn the_default_serialises_to_toml_and_back() {
    let text = toml::to_string(&TwinConfig::default()).unwrap();
    assert_eq!(toml::from_str::<TwinConfig>(&text).unwrap(), TwinConfig::default());
}

#[test]
fn a_partial_scenario_table_keeps_the_twins_trocars() {
    let c: TwinConfig = toml::from_str("[scenario]\nseed = 9\n").unwrap();
    assert_eq!(c.scenario.trocars_base_m, sim::twin::DEFAULT_TROCARS_BASE_M.to_vec());
    assert_eq!(c.scenario.seed, 9);
}
