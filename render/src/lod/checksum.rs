//! The 64-bit checksum of stored nodes and hierarchies.
//!
//! Not cryptographic: it guards against damaged bytes, not against an attacker. Each 8-byte
//! word passes through a bijective mix and is folded into the state by a bijective step, so
//! changing any single word (or byte) always changes the sum; the length is mixed in too.

const P1: u64 = 0x9E37_79B1_85EB_CA87;
const P2: u64 = 0xC2B2_AE3D_27D4_EB4F;
const P3: u64 = 0x1656_67B1_9E37_79F9;

fn mix(word: u64) -> u64 {
    (word ^ (word >> 31)).wrapping_mul(P2).rotate_left(29)
}

/// The checksum of `bytes`, seeded (for example with the node's key, so a node stored under
/// another key does not pass).
pub fn checksum64(seed: &[u8], bytes: &[u8]) -> u64 {
    let mut state = P3 ^ (bytes.len() as u64).wrapping_mul(P1);
    let fold = |state: &mut u64, chunk: &[u8]| {
        let mut word = [0; 8];
        word[..chunk.len()].copy_from_slice(chunk);
        *state = (*state ^ mix(u64::from_le_bytes(word)))
            .rotate_left(27)
            .wrapping_mul(P1)
            .wrapping_add(P2);
    };
    for part in [seed, bytes] {
        let mut chunks = part.chunks_exact(8);
        for chunk in &mut chunks {
            fold(&mut state, chunk);
        }
        let rest = chunks.remainder();
        // The remainder's length is folded in as well, so a trailing zero byte counts.
        fold(&mut state, &[rest.len() as u8]);
        if !rest.is_empty() {
            fold(&mut state, rest);
        }
    }
    state ^= state >> 33;
    state = state.wrapping_mul(P2);
    state ^= state >> 29;
    state = state.wrapping_mul(P3);
    state ^ (state >> 32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_single_byte_change_changes_the_sum() {
        let bytes: Vec<u8> = (0..203u32).map(|i| (i * 31 % 251) as u8).collect();
        let sum = checksum64(b"key", &bytes);
        for i in 0..bytes.len() {
            for flip in [1u8, 0x80, 0xff] {
                let mut damaged = bytes.clone();
                damaged[i] ^= flip;
                assert_ne!(checksum64(b"key", &damaged), sum, "byte {i} ^ {flip}");
            }
        }
        assert_ne!(checksum64(b"kez", &bytes), sum);
        assert_ne!(checksum64(b"key", &bytes[..202]), sum);
    }
}
