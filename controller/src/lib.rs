//! comanip's processes.
