//! Shared-memory output of fulcrumd (iceoryx2 publish-subscribe).

mod message;

pub use message::{FULCRUM_SAMPLE_VERSION, FulcrumSample, STATE_INSIDE, STATE_INVALID, STATE_OUTSIDE, health};
