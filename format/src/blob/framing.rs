//! Preamble, header CRC, padding and payload CRC: everything up to the
//! point where the payload's bytes can be trusted.

#![deny(clippy::arithmetic_side_effects)]

use crate::blob::{Header, NodeTable};
use crate::error::{Error, Result};

/// First four bytes of every blob.
pub const MAGIC: [u8; 4] = *b"PGMB";
/// The format version this runtime writes and reads.
pub const FORMAT_VERSION: u16 = 2;
/// Bytes before the postcard header: magic, version, header length, header CRC.
pub const PREAMBLE_LEN: usize = 12;
/// The payload starts at a multiple of this, counted from the blob's first byte.
pub const PAYLOAD_ALIGN: usize = 16;

const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// CRC-32 (ISO-HDLC: the one of zlib, PNG and Ethernet) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    CRC.checksum(bytes)
}

/// A blob whose framing and checksums have been verified.
pub struct Framed<'a> {
    /// The decoded header (its nodes still in the blob's bytes).
    pub header: Header<NodeTable<'a>>,
    /// The payload bytes (CRC verified).
    pub payload: &'a [u8],
    /// Length of the whole blob.
    pub blob_len: usize,
}

struct Preamble {
    header_len: usize,
    header_crc: u32,
}

fn le_u16(bytes: &[u8], at: usize) -> Option<u16> {
    let b = bytes.get(at..at.checked_add(2)?)?;
    Some(u16::from_le_bytes([*b.first()?, *b.get(1)?]))
}

fn le_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let b: [u8; 4] = bytes.get(at..at.checked_add(4)?)?.try_into().ok()?;
    Some(u32::from_le_bytes(b))
}

fn truncated(needed: usize, available: usize) -> Error {
    Error::Truncated {
        needed: u32::try_from(needed).unwrap_or(u32::MAX),
        available: u32::try_from(available).unwrap_or(u32::MAX),
    }
}

fn read_preamble(bytes: &[u8]) -> Result<Preamble> {
    let magic = bytes
        .get(..MAGIC.len())
        .ok_or(truncated(PREAMBLE_LEN, bytes.len()))?;
    if magic != MAGIC {
        return Err(Error::BadMagic);
    }
    let (Some(version), Some(header_len), Some(header_crc)) =
        (le_u16(bytes, 4), le_u16(bytes, 6), le_u32(bytes, 8))
    else {
        return Err(truncated(PREAMBLE_LEN, bytes.len()));
    };
    if version != FORMAT_VERSION {
        return Err(Error::UnsupportedVersion {
            found: version,
            supported: FORMAT_VERSION,
        });
    }
    Ok(Preamble {
        header_len: usize::from(header_len),
        header_crc,
    })
}

/// Checks the header CRC and decodes it; returns the header and where the
/// payload starts.
fn read_header(bytes: &[u8]) -> Result<(Header<NodeTable<'_>>, usize)> {
    let pre = read_preamble(bytes)?;
    // Cannot overflow: 12 + a u16.
    #[allow(clippy::arithmetic_side_effects)]
    let header_end = PREAMBLE_LEN + pre.header_len;
    let header_bytes = bytes
        .get(PREAMBLE_LEN..header_end)
        .ok_or(truncated(header_end, bytes.len()))?;
    let mut digest = CRC.digest();
    digest.update(bytes.get(..8).ok_or(truncated(PREAMBLE_LEN, bytes.len()))?);
    digest.update(header_bytes);
    if digest.finalize() != pre.header_crc {
        return Err(Error::HeaderCorrupt);
    }
    let header = Header::parse(header_bytes)?;
    Ok((header, header_end.next_multiple_of(PAYLOAD_ALIGN)))
}

/// The header of the blob that starts `prefix` (preamble and header
/// checked, CRC included; the payload need not be there yet): what kind
/// of blob a flash region holds before it is loaded as one.
pub fn header_from_prefix(prefix: &[u8]) -> Result<Header<NodeTable<'_>>> {
    read_header(prefix).map(|(header, _)| header)
}

/// Length of the blob that starts `prefix`, read from its preamble and
/// header alone (the payload need not be there yet). Lets firmware find
/// the blob inside a larger flash region.
pub fn blob_len_from_prefix(prefix: &[u8]) -> Result<usize> {
    let (header, payload_start) = read_header(prefix)?;
    payload_start
        .checked_add(header.payload_len as usize)
        .ok_or(truncated(usize::MAX, prefix.len()))
}

impl<'a> Framed<'a> {
    /// Verifies magic, version, header CRC, padding and payload CRC.
    /// `exact`: the slice must end where the payload ends.
    pub fn parse(bytes: &'a [u8], exact: bool) -> Result<Self> {
        let (header, payload_start) = read_header(bytes)?;
        let padding = bytes
            .get(PREAMBLE_LEN..payload_start)
            .ok_or(truncated(payload_start, bytes.len()))?;
        let header_len = usize::from(le_u16(bytes, 6).unwrap_or(0));
        if padding.iter().skip(header_len).any(|&b| b != 0) {
            return Err(Error::HeaderMalformed);
        }
        let blob_len = payload_start
            .checked_add(header.payload_len as usize)
            .ok_or(truncated(usize::MAX, bytes.len()))?;
        let payload = bytes
            .get(payload_start..blob_len)
            .ok_or(truncated(blob_len, bytes.len()))?;
        if exact && bytes.len() != blob_len {
            return Err(Error::TrailingBytes {
                blob_len: u32::try_from(blob_len).unwrap_or(u32::MAX),
                found: u32::try_from(bytes.len()).unwrap_or(u32::MAX),
            });
        }
        if crc32(payload) != header.payload_crc {
            return Err(Error::PayloadCorrupt);
        }
        Ok(Framed {
            header,
            payload,
            blob_len,
        })
    }
}
