//! cargo-fuzz target `calib_json`: `comanip_fuzz::TARGETS`'s body of the same name (docs/fuzzing.md).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    (comanip_fuzz::target("calib_json").expect("a target of comanip_fuzz").run)(data);
});
