// The high-quality resolve's sums after the 32-bit accumulation (hq_sums_atomic32.wgsl): the
// accumulator's four words a pixel. Composed after resolve.wgsl.

fn read_sums(pixel: u32) -> vec4<u32> {
    return accumulator[pixel];
}

fn empty_sums(pixel: u32) {
    accumulator[pixel] = vec4<u32>(0u);
}
