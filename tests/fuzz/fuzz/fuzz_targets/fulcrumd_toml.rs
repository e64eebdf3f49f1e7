//! cargo-fuzz target `fulcrumd_toml`: `comanip_fuzz::TARGETS`'s body of the same name (docs/fuzzing.md).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    (comanip_fuzz::target("fulcrumd_toml").expect("a target of comanip_fuzz").run)(data);
});
