//! A MessagePack reader for what `flax.serialization.to_bytes` writes: nested maps with string
//! keys, integers, floats, strings, binary, and extension values (flax stores each array as
//! extension 1). Values borrow from the input so a multi-gigabyte checkpoint is not copied.
//!
//! Written here rather than taken from a crate: the subset is small, and reading borrowed
//! extension payloads is all the importer needs.

/// One decoded value.
#[derive(Debug, Clone, PartialEq)]
pub enum Value<'a> {
    /// `nil`.
    Nil,
    /// `true` / `false`.
    Bool(bool),
    /// Any integer (msgpack's unsigned 64-bit values above `i64::MAX` are refused).
    Int(i64),
    /// `float32` or `float64`.
    Float(f64),
    /// UTF-8 text.
    Str(&'a str),
    /// Raw bytes.
    Bin(&'a [u8]),
    /// An ordered list.
    Array(Vec<Value<'a>>),
    /// Key/value pairs in stored order.
    Map(Vec<(Value<'a>, Value<'a>)>),
    /// An extension: type code and payload.
    Ext(i8, &'a [u8]),
}

/// Why bytes could not be read as MessagePack.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("msgpack at byte {offset}: {reason}")]
pub struct MsgpackError {
    /// Where reading failed.
    pub offset: usize,
    /// What was wrong there.
    pub reason: String,
}

/// Nesting deeper than this is refused rather than risking the stack on hostile input.
const MAX_DEPTH: usize = 256;

/// Decodes one value that must span all of `bytes`.
pub fn decode(bytes: &[u8]) -> Result<Value<'_>, MsgpackError> {
    let mut reader = Reader { bytes, offset: 0 };
    let value = reader.value(0)?;
    if reader.offset != bytes.len() {
        return Err(reader.error(format!(
            "{} trailing bytes after the value",
            bytes.len() - reader.offset
        )));
    }
    Ok(value)
}

struct Reader<'a> {
    bytes: &'a [u8],
    offset: usize,
}

impl<'a> Reader<'a> {
    fn error(&self, reason: String) -> MsgpackError {
        MsgpackError {
            offset: self.offset,
            reason,
        }
    }

    fn take(&mut self, count: usize) -> Result<&'a [u8], MsgpackError> {
        let end = self
            .offset
            .checked_add(count)
            .filter(|&end| end <= self.bytes.len())
            .ok_or_else(|| self.error(format!("needs {count} more bytes than the input has")))?;
        let slice = &self.bytes[self.offset..end];
        self.offset = end;
        Ok(slice)
    }

    fn uint(&mut self, width: usize) -> Result<u64, MsgpackError> {
        Ok(self
            .take(width)?
            .iter()
            .fold(0u64, |acc, &b| (acc << 8) | u64::from(b)))
    }

    fn length(&mut self, width: usize) -> Result<usize, MsgpackError> {
        let n = self.uint(width)?;
        usize::try_from(n).map_err(|_| self.error(format!("length {n} does not fit")))
    }

    fn str(&mut self, len: usize) -> Result<Value<'a>, MsgpackError> {
        let start = self.offset;
        let raw = self.take(len)?;
        std::str::from_utf8(raw)
            .map(Value::Str)
            .map_err(|e| MsgpackError {
                offset: start,
                reason: format!("string is not UTF-8: {e}"),
            })
    }

    fn ext(&mut self, len: usize) -> Result<Value<'a>, MsgpackError> {
        let code = self.take(1)?[0] as i8;
        Ok(Value::Ext(code, self.take(len)?))
    }

    fn array(&mut self, len: usize, depth: usize) -> Result<Value<'a>, MsgpackError> {
        let mut items = Vec::with_capacity(len.min(1 << 16));
        for _ in 0..len {
            items.push(self.value(depth + 1)?);
        }
        Ok(Value::Array(items))
    }

    fn map(&mut self, len: usize, depth: usize) -> Result<Value<'a>, MsgpackError> {
        let mut entries = Vec::with_capacity(len.min(1 << 16));
        for _ in 0..len {
            let key = self.value(depth + 1)?;
            let value = self.value(depth + 1)?;
            entries.push((key, value));
        }
        Ok(Value::Map(entries))
    }

    fn signed(&mut self, width: usize) -> Result<Value<'a>, MsgpackError> {
        let raw = self.uint(width)?;
        let shift = 64 - 8 * width as u32;
        Ok(Value::Int(((raw << shift) as i64) >> shift))
    }

    fn value(&mut self, depth: usize) -> Result<Value<'a>, MsgpackError> {
        if depth > MAX_DEPTH {
            return Err(self.error(format!("nested deeper than {MAX_DEPTH}")));
        }
        let marker = self.take(1)?[0];
        Ok(match marker {
            0x00..=0x7f => Value::Int(i64::from(marker)),
            0x80..=0x8f => self.map(usize::from(marker & 0x0f), depth)?,
            0x90..=0x9f => self.array(usize::from(marker & 0x0f), depth)?,
            0xa0..=0xbf => self.str(usize::from(marker & 0x1f))?,
            0xc0 => Value::Nil,
            0xc2 => Value::Bool(false),
            0xc3 => Value::Bool(true),
            0xc4..=0xc6 => {
                let len = self.length(1 << (marker - 0xc4))?;
                Value::Bin(self.take(len)?)
            }
            0xc7..=0xc9 => {
                let len = self.length(1 << (marker - 0xc7))?;
                self.ext(len)?
            }
            0xca => Value::Float(f64::from(f32::from_bits(self.uint(4)? as u32))),
            0xcb => Value::Float(f64::from_bits(self.uint(8)?)),
            0xcc..=0xcf => {
                let n = self.uint(1 << (marker - 0xcc))?;
                Value::Int(
                    i64::try_from(n).map_err(|_| self.error(format!("integer {n} too large")))?,
                )
            }
            0xd0..=0xd3 => self.signed(1 << (marker - 0xd0))?,
            0xd4..=0xd8 => self.ext(1 << (marker - 0xd4))?,
            0xd9..=0xdb => {
                let len = self.length(1 << (marker - 0xd9))?;
                self.str(len)?
            }
            0xdc | 0xdd => {
                let len = self.length(if marker == 0xdc { 2 } else { 4 })?;
                self.array(len, depth)?
            }
            0xde | 0xdf => {
                let len = self.length(if marker == 0xde { 2 } else { 4 })?;
                self.map(len, depth)?
            }
            0xe0..=0xff => Value::Int(i64::from(marker as i8)),
            0xc1 => return Err(self.error("marker 0xc1 is never used".to_string())),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decodes_maps_ints_strings_floats_and_extensions() {
        // {"a": [1, -2, 300], "b": 1.5, "c": ext(1, b"xy")}
        let bytes = [
            0x83, 0xa1, b'a', 0x93, 0x01, 0xfe, 0xcd, 0x01, 0x2c, 0xa1, b'b', 0xcb, 0x3f, 0xf8, 0,
            0, 0, 0, 0, 0, 0xa1, b'c', 0xd5, 0x01, b'x', b'y',
        ];
        let value = decode(&bytes).unwrap();
        let Value::Map(entries) = value else {
            panic!("not a map: {value:?}");
        };
        assert_eq!(entries[0].0, Value::Str("a"));
        assert_eq!(
            entries[0].1,
            Value::Array(vec![Value::Int(1), Value::Int(-2), Value::Int(300)])
        );
        assert_eq!(entries[1].1, Value::Float(1.5));
        assert_eq!(entries[2].1, Value::Ext(1, b"xy"));
    }

    #[test]
    fn truncated_and_trailing_input_is_refused_with_its_offset() {
        let error = decode(&[0x92, 0x01]).unwrap_err();
        assert_eq!(error.offset, 2, "{error}");
        assert!(
            decode(&[0x01, 0x02])
                .unwrap_err()
                .reason
                .contains("trailing")
        );
        assert!(decode(&[0xd1, 0xff]).is_err());
        assert_eq!(decode(&[0xd1, 0xff, 0x38]).unwrap(), Value::Int(-200));
    }
}
