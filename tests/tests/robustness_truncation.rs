//! Truncated blobs and trailing bytes: refused with the length they need.

mod hostile;

use hostile::*;

#[test]
fn every_truncation_is_refused_with_the_length_it_needs() {
    for blob in [
        quantised(WeightFormat::I8),
        quantised(WeightFormat::I16),
        hand_blob(),
    ] {
        let header_end = 12 + usize::from(u16::from_le_bytes([blob[6], blob[7]]));
        let start = payload_start(&blob);
        for n in 0..blob.len() {
            let needed = if n < 12 {
                12
            } else if n < header_end {
                header_end
            } else if n < start {
                start
            } else {
                blob.len()
            };
            let want = Error::Truncated {
                needed: needed as u32,
                available: n as u32,
            };
            assert_eq!(
                Model::from_bytes(&blob[..n]).unwrap_err(),
                want,
                "prefix {n}"
            );
            assert_eq!(
                Model::from_region(&blob[..n]).unwrap_err(),
                want,
                "prefix {n}"
            );
            let from_prefix = blob_len_from_prefix(&blob[..n]);
            if n >= header_end {
                assert_eq!(from_prefix, Ok(blob.len()));
            } else {
                assert_eq!(from_prefix.unwrap_err(), want);
            }
        }
        assert!(Model::from_bytes(&blob).is_ok());
    }
}

#[test]
fn trailing_bytes_are_refused_by_from_bytes_and_ignored_by_from_region() {
    let blob = hand_blob();
    for extra in [&[0u8][..], &[0xFF; 3], &blob[..]] {
        let mut longer = blob.clone();
        longer.extend_from_slice(extra);
        let want = Error::TrailingBytes {
            blob_len: blob.len() as u32,
            found: longer.len() as u32,
        };
        assert_eq!(Model::from_bytes(&longer).unwrap_err(), want);
        assert_eq!(Model::from_region(&longer).unwrap().blob_len(), blob.len());
    }
}
