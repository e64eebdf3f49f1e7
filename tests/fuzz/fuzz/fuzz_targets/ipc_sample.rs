//! cargo-fuzz target `ipc_sample`: `comanip_fuzz::TARGETS`'s body of the same name (docs/fuzzing.md).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    (comanip_fuzz::target("ipc_sample").expect("a target of comanip_fuzz").run)(data);
});
