//! cargo-fuzz target `frame_header`: `comanip_fuzz::TARGETS`'s body of the same name (docs/fuzzing.md).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    (comanip_fuzz::target("frame_header").expect("a target of comanip_fuzz").run)(data);
});
