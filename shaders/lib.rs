//! WGSL sources of the renderer, embedded at build time.
