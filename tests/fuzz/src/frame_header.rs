//! The camera frame header (`hw_io::ipc::FrameHeader::meta`, what a frame subscriber checks on
//! every sample): 72 arbitrary bytes and an arbitrary payload length.

use hw_io::ipc::FrameHeader;

use crate::Bytes;

/// `data` as a header (72 bytes, little-endian, the C layout's order) then the payload's
/// length (`u32`); a typed error, or metadata that is consistent with the header and the
/// payload and rebuilds the same header.
pub fn run(data: &[u8]) {
    let mut b = Bytes::new(data);
    let header = FrameHeader {
        version: b.u32(),
        camera_id: b.u32(),
        sequence: b.u64(),
        run_id: b.u64(),
        timestamp_ns: b.u64(),
        exposure_ns: b.u32(),
        eyes: b.u32(),
        width: b.u32(),
        height: b.u32(),
        stride: b.u32(),
        pixel_format: b.u32(),
        payload_bytes: b.u64(),
        source_dropped: b.u64(),
    };
    let payload_len = b.u32() as usize;
    let Ok(meta) = header.meta(payload_len) else { return };
    assert!(meta.format().validate().is_ok(), "accepted an invalid format: {meta:?}");
    assert!(meta.layout.stride as usize >= meta.layout.row_bytes());
    assert_eq!(meta.payload_bytes(), payload_len);
    assert_eq!(meta.payload_bytes() as u64, header.payload_bytes);
    assert_eq!(FrameHeader::new(&meta, header.run_id, header.source_dropped), header);
}
