// The high-quality resolve's sums after the 64-bit accumulation (hq_sums_atomic64.wgsl): per
// pixel the packed sums, 16 bits each (red, green, blue, count), and where their flag is set
// the wide sums too. Composed after resolve.wgsl.

// Zeroed as they are read, like the framebuffer.
@group(0) @binding(5) var<storage, read_write> packed_sums: array<vec2<u32>>;

// The flag of a packed word that says the wide sums hold points too (bit 63).
const WIDE_SUMS_USED: u32 = 0x80000000u;

fn read_sums(pixel: u32) -> vec4<u32> {
    let packed = packed_sums[pixel];
    var sums = vec4<u32>(packed.x & 0xffffu, packed.x >> 16u, packed.y & 0xffffu, (packed.y >> 16u) & 0x7fffu);
    // Rare: only pixels with more than `PACKED_POINTS` points in the depth band use them
    // (hq_sums_atomic64.wgsl); emptied here, where they are known to be used.
    if (packed.y & WIDE_SUMS_USED) != 0u {
        sums += accumulator[pixel];
        accumulator[pixel] = vec4<u32>(0u);
    }
    return sums;
}

fn empty_sums(pixel: u32) {
    packed_sums[pixel] = vec2<u32>(0u);
}
