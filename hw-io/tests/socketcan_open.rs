//! SocketCAN backend against the running kernel.
//!
//! This machine's kernel has no CAN support: opening any CAN socket fails with
//! EAFNOSUPPORT, which must come out as `OpenError::NoKernelCan` with a message saying
//! what to do. On a kernel with CAN (the vcan hardware-in-loop suite), an unknown interface
//! must come out as `OpenError::NoSuchInterface` instead.

use hw_io::can::{OpenError, SocketCanBus};

/// `/proc/net/can` exists exactly when the `can` protocol family is registered.
fn kernel_has_can() -> bool {
    std::path::Path::new("/proc/net/can").exists()
}

#[test]
fn missing_kernel_support_or_interface_is_a_clear_typed_error() {
    let err = SocketCanBus::open("vcan0").err();
    if kernel_has_can() {
        // The interface may or may not exist here; an interface that surely does not:
        let err = SocketCanBus::open("comanipnone0").unwrap_err();
        assert!(matches!(err, OpenError::NoSuchInterface { .. }), "{err:?}");
        assert!(err.to_string().contains("ip link add dev comanipnone0 type vcan"), "{err}");
        return;
    }
    let err = err.expect("opening vcan0 must fail on a kernel without CAN support");
    match &err {
        OpenError::NoKernelCan { interface, source } => {
            assert_eq!(interface, "vcan0");
            // Whether the interface lookup or socket() failed first, the error carried is
            // socket(AF_CAN)'s EAFNOSUPPORT (97 on Linux).
            assert_eq!(source.raw_os_error(), Some(97), "{source:?}");
        }
        other => panic!("expected NoKernelCan, got {other:?}"),
    }
    let msg = err.to_string();
    println!("{msg}");
    assert!(msg.contains("kernel has no CAN support"), "{msg}");
    assert!(msg.contains("modprobe") && msg.contains("vcan"), "{msg}");
    // Same for an interface name that exists but is not CAN ("lo").
    assert!(matches!(SocketCanBus::open("lo"), Err(OpenError::NoKernelCan { .. })));
}
