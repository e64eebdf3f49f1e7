//! cargo-fuzz target `acquisition`: `comanip_fuzz::TARGETS`'s body of the same name (docs/fuzzing.md).
#![no_main]

// The counting allocator: the acquisition target asserts that the cycle path allocates nothing.
#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    (comanip_fuzz::target("acquisition").expect("a target of comanip_fuzz").run)(data);
});
