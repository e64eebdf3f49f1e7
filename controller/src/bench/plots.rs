//! SVG figures of the benchmark (plotters).
