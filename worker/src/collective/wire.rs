//! How a chunk's values travel: float32, or bf16 (opt-in, half the bytes) summed in float32.
//!
//! A buffer may end in values that must stay exact whatever the wire (the loss terms behind
//! the gradients): `exact_from` is the first of them, and a chunk carries the values before
//! it in the wire's type and the rest in float32.
//!
//! With bf16, every rank must still end with the same bits: the owner of a segment rounds its
//! fully reduced values to bf16 in place ([`Encoding::round_owned`]) before it sends them
//! around the all-gather, so it keeps exactly what the others decode.

use bytes::Bytes;
pub use settings::work::WireFormat;

/// The encoding of one all-reduce: its wire type and where its exact values start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Encoding {
    pub(super) wire: WireFormat,
    pub(super) exact_from: usize,
}

/// Bytes of one value of `wire`.
fn width(wire: WireFormat) -> usize {
    match wire {
        WireFormat::F32 => 4,
        WireFormat::Bf16 => 2,
    }
}

impl Encoding {
    /// Values of `begin..end` that travel in the wire's type (the rest are float32).
    fn wire_values(&self, begin: usize, end: usize) -> usize {
        self.exact_from.clamp(begin, end) - begin
    }

    /// Whether values `begin..end` travel as the float32 bytes they are in memory (so a chunk
    /// can be written from the buffer and read into it as it lies).
    pub(super) fn is_plain(&self, begin: usize, end: usize) -> bool {
        cfg!(target_endian = "little")
            && (self.wire == WireFormat::F32 || self.wire_values(begin, end) == 0)
    }

    /// Bytes of the chunk of values `begin..end`.
    pub(super) fn chunk_bytes(&self, begin: usize, end: usize) -> usize {
        let wired = self.wire_values(begin, end);
        wired * width(self.wire) + (end - begin - wired) * 4
    }

    /// The chunk of `values`, which are the buffer's values from `begin` on: float32 values
    /// are copied as they lie in memory (one `memcpy` on a little-endian host), bf16 ones
    /// rounded into place.
    pub(super) fn encode(&self, begin: usize, values: &[f32]) -> Bytes {
        let mut bytes = Vec::new();
        self.encode_into(begin, values, &mut bytes);
        Bytes::from(bytes)
    }

    /// [`Encoding::encode`] into `bytes`, which it replaces (a lane reuses one buffer).
    pub(super) fn encode_into(&self, begin: usize, values: &[f32], bytes: &mut Vec<u8>) {
        let wired = self.wire_values(begin, begin + values.len());
        bytes.clear();
        bytes.reserve(self.chunk_bytes(begin, begin + values.len()));
        match self.wire {
            WireFormat::F32 => extend_f32(bytes, &values[..wired]),
            WireFormat::Bf16 => {
                bytes.resize(wired * 2, 0);
                bytes
                    .chunks_exact_mut(2)
                    .zip(&values[..wired])
                    .for_each(|(slot, value)| slot.copy_from_slice(&to_bf16(*value).to_le_bytes()));
            }
        }
        extend_f32(bytes, &values[wired..]);
    }

    /// `target += chunk` (reduce-scatter) or `target = chunk` (all-gather), where `target` is
    /// the buffer's values from `begin` on and `chunk` was checked to be their size.
    pub(super) fn absorb(&self, begin: usize, target: &mut [f32], chunk: &[u8], add: bool) {
        let wired = self.wire_values(begin, begin + target.len());
        let (head, tail) = target.split_at_mut(wired);
        let split = wired * width(self.wire);
        let merge = |slot: &mut f32, value: f32| {
            if add {
                *slot += value;
            } else {
                *slot = value;
            }
        };
        match self.wire {
            WireFormat::F32 => head
                .iter_mut()
                .zip(chunk[..split].chunks_exact(4))
                .for_each(|(slot, raw)| merge(slot, f32_of(raw))),
            WireFormat::Bf16 => head
                .iter_mut()
                .zip(chunk[..split].chunks_exact(2))
                .for_each(|(slot, raw)| {
                    merge(slot, from_bf16(u16::from_le_bytes([raw[0], raw[1]])))
                }),
        }
        tail.iter_mut()
            .zip(chunk[split..].chunks_exact(4))
            .for_each(|(slot, raw)| merge(slot, f32_of(raw)));
    }

    /// Rounds the owner's fully reduced values (the buffer's from `begin` on) to what the
    /// wire carries, so that the owner keeps what every other rank will decode.
    pub(super) fn round_owned(&self, begin: usize, values: &mut [f32]) {
        if self.wire == WireFormat::Bf16 {
            let wired = self.wire_values(begin, begin + values.len());
            values[..wired]
                .iter_mut()
                .for_each(|value| *value = from_bf16(to_bf16(*value)));
        }
    }
}

/// `values` appended to `bytes` as little-endian float32.
fn extend_f32(bytes: &mut Vec<u8>, values: &[f32]) {
    if cfg!(target_endian = "little") {
        bytes.extend_from_slice(float_bytes(values));
    } else {
        bytes.extend(values.iter().flat_map(|value| value.to_le_bytes()));
    }
}

/// The bytes of `values` as they lie in memory: little-endian float32 on a little-endian
/// host, which is where both transports use them ([`Encoding::is_plain`] is false elsewhere).
/// The one place the ring views floats as bytes.
pub(super) fn float_bytes(values: &[f32]) -> &[u8] {
    // SAFETY: an f32 is 4 initialised bytes without padding, a u8 needs no alignment, and the
    // slice covers exactly the values' memory for as long as `values` is borrowed.
    unsafe { std::slice::from_raw_parts(values.as_ptr().cast::<u8>(), size_of_val(values)) }
}

/// The bytes of `values`, writable: every bit pattern written is some f32.
pub(super) fn float_bytes_mut(values: &mut [f32]) -> &mut [u8] {
    // SAFETY: as in `float_bytes`, and any 4 bytes are a valid f32, so whatever is written
    // through the byte view leaves valid values; the view borrows `values` mutably.
    unsafe { std::slice::from_raw_parts_mut(values.as_mut_ptr().cast::<u8>(), size_of_val(values)) }
}

fn f32_of(raw: &[u8]) -> f32 {
    f32::from_le_bytes([raw[0], raw[1], raw[2], raw[3]])
}

/// `value` rounded to the nearest bf16, ties to even (as JAX and PyTorch convert); NaN stays
/// NaN.
pub(crate) fn to_bf16(value: f32) -> u16 {
    let bits = value.to_bits();
    if value.is_nan() {
        return ((bits >> 16) | 0x0040) as u16;
    }
    let rounding = 0x7fff + ((bits >> 16) & 1);
    (bits.wrapping_add(rounding) >> 16) as u16
}

/// The float32 of a bf16 (exact).
pub(crate) fn from_bf16(half: u16) -> f32 {
    f32::from_bits(u32::from(half) << 16)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bf16_rounds_to_nearest_even() {
        assert_eq!(from_bf16(to_bf16(1.0)), 1.0);
        // 1 + 2^-8 lies halfway between 1 and 1 + 2^-7: ties go to the even one, 1.
        assert_eq!(from_bf16(to_bf16(1.0 + 1.0 / 256.0)), 1.0);
        assert_eq!(from_bf16(to_bf16(1.0 + 3.0 / 256.0)), 1.0 + 4.0 / 256.0);
        // bf16 keeps float32's exponent: gradients near 5e-9 (the paper model's LayerScale
        // branches) do not underflow as they would in f16.
        let tiny = from_bf16(to_bf16(-2.5e-9));
        assert!((tiny + 2.5e-9).abs() <= 2.5e-9 / 256.0, "{tiny:e}");
        assert!(from_bf16(to_bf16(f32::NAN)).is_nan());
        assert_eq!(from_bf16(to_bf16(f32::INFINITY)), f32::INFINITY);
        let relative = (from_bf16(to_bf16(0.1)) - 0.1).abs() / 0.1;
        assert!(relative <= 1.0 / 256.0, "{relative}");
    }

    #[test]
    fn exact_values_travel_in_float32_whatever_the_wire() {
        let encoding = Encoding {
            wire: WireFormat::Bf16,
            exact_from: 6,
        };
        let values = [0.1f32, 0.2, 0.3, 0.4];
        // Values 4..8 of a buffer whose last two (6, 7) are exact.
        assert_eq!(encoding.chunk_bytes(4, 8), 2 * 2 + 2 * 4);
        let chunk = encoding.encode(4, &values);
        assert_eq!(chunk.len(), 12);
        let mut target = [1.0f32; 4];
        encoding.absorb(4, &mut target, &chunk, true);
        assert_eq!(target[2..], [1.3, 1.4]);
        assert_eq!(target[0], 1.0 + from_bf16(to_bf16(0.1)));
        encoding.absorb(4, &mut target, &chunk, false);
        assert_eq!(target[2..], [0.3, 0.4]);
        let mut owned = values;
        encoding.round_owned(4, &mut owned);
        assert_eq!(
            owned,
            [from_bf16(to_bf16(0.1)), from_bf16(to_bf16(0.2)), 0.3, 0.4]
        );
    }

    #[test]
    fn float32_chunks_carry_every_bit() {
        let encoding = Encoding {
            wire: WireFormat::F32,
            exact_from: usize::MAX,
        };
        let values = [1.0f32 / 3.0, -0.0, f32::MIN_POSITIVE, 7e30];
        let chunk = encoding.encode(0, &values);
        assert_eq!(chunk.len(), encoding.chunk_bytes(0, 4));
        let mut target = [0.0f32; 4];
        encoding.absorb(0, &mut target, &chunk, false);
        assert_eq!(target.map(f32::to_bits), values.map(f32::to_bits));
        let mut owned = values;
        encoding.round_owned(0, &mut owned);
        assert_eq!(owned, values, "float32 rounds nothing");
    }
}
