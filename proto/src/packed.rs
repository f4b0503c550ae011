//! Bulk arrays as one block of little-endian bytes (`#[serde(with = "packed")]`).
//!
//! Serde would otherwise visit every element (a call per `f32`); here a whole array is one
//! `serialize_bytes` call, which postcard writes as a varint length and a `memcpy`. Decoding
//! borrows the bytes from the frame and copies them once into a properly aligned `Vec`.
//! On big-endian hosts the words are swapped so that the wire stays little-endian.

use std::fmt;
use std::marker::PhantomData;

use bytemuck::Pod;
use serde::de::{Error as _, SeqAccess, Visitor};
use serde::{Deserializer, Serializer};

/// Element types made of 4-byte little-endian words (`u32`, `f32`, `[f32; 3]`).
pub trait Words: Pod {}
impl Words for u32 {}
impl Words for f32 {}
impl Words for [f32; 3] {}

pub fn serialize<T: Words, S: Serializer>(values: &[T], serializer: S) -> Result<S::Ok, S::Error> {
    #[cfg(target_endian = "little")]
    {
        serializer.serialize_bytes(bytemuck::cast_slice(values))
    }
    #[cfg(target_endian = "big")]
    {
        let words: &[u32] = bytemuck::cast_slice(values);
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        serializer.serialize_bytes(&bytes)
    }
}

pub fn deserialize<'de, T: Words, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<T>, D::Error> {
    deserializer.deserialize_bytes(PackedVisitor(PhantomData))
}

/// Copies little-endian bytes into a `Vec<T>`; `None` if the length is not a whole number
/// of elements.
pub(crate) fn from_le_bytes<T: Words>(bytes: &[u8]) -> Option<Vec<T>> {
    let size = size_of::<T>();
    if bytes.len() / size * size != bytes.len() {
        return None;
    }
    #[cfg(target_endian = "little")]
    {
        Some(bytemuck::pod_collect_to_vec(bytes))
    }
    #[cfg(target_endian = "big")]
    {
        let words: Vec<u32> = bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        Some(bytemuck::pod_collect_to_vec(&words))
    }
}

struct PackedVisitor<T>(PhantomData<T>);

impl<'de, T: Words> Visitor<'de> for PackedVisitor<T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "a packed array of {}-byte elements", size_of::<T>())
    }

    fn visit_bytes<E: serde::de::Error>(self, bytes: &[u8]) -> Result<Vec<T>, E> {
        from_le_bytes(bytes).ok_or_else(|| E::invalid_length(bytes.len(), &self))
    }

    fn visit_borrowed_bytes<E: serde::de::Error>(self, bytes: &'de [u8]) -> Result<Vec<T>, E> {
        self.visit_bytes(bytes)
    }

    fn visit_byte_buf<E: serde::de::Error>(self, bytes: Vec<u8>) -> Result<Vec<T>, E> {
        self.visit_bytes(&bytes)
    }

    /// Self-describing formats without a bytes type (JSON) send a sequence of numbers.
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        // Never trust a size hint for the allocation: grow as elements arrive.
        let mut bytes = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(4096));
        while let Some(b) = seq.next_element::<u8>()? {
            bytes.push(b);
        }
        from_le_bytes(&bytes).ok_or_else(|| A::Error::invalid_length(bytes.len(), &self))
    }
}

/// A plain byte array as one block (`#[serde(with = "packed::bytes")]`).
pub mod bytes {
    use std::fmt;

    use serde::de::{SeqAccess, Visitor};
    use serde::{Deserializer, Serializer};

    pub fn serialize<S: Serializer>(values: &[u8], serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_bytes(values)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u8>, D::Error> {
        deserializer.deserialize_bytes(BytesVisitor)
    }

    struct BytesVisitor;

    impl<'de> Visitor<'de> for BytesVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("a byte array")
        }

        fn visit_bytes<E: serde::de::Error>(self, bytes: &[u8]) -> Result<Vec<u8>, E> {
            Ok(bytes.to_vec())
        }

        fn visit_byte_buf<E: serde::de::Error>(self, bytes: Vec<u8>) -> Result<Vec<u8>, E> {
            Ok(bytes)
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<u8>, A::Error> {
            let mut bytes = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(4096));
            while let Some(b) = seq.next_element::<u8>()? {
                bytes.push(b);
            }
            Ok(bytes)
        }
    }
}
