//! Decoding the firmware's defmt stream (semihosting stdout) with
//! `defmt-decoder` and the format strings in the firmware ELF.

use anyhow::{anyhow, Result};
use defmt_decoder::{DecodeError, Table};

/// Decodes `stream` into one line per log frame: `LEVEL message`.
/// Undecodable trailing bytes become a final note line.
pub fn decode(elf: &[u8], stream: &[u8]) -> Result<Vec<String>> {
    let table = Table::parse(elf)
        .map_err(|e| anyhow!("cannot read the defmt table of the firmware: {e}"))?
        .ok_or_else(|| anyhow!("the firmware ELF has no .defmt section"))?;
    let mut decoder = table.new_stream_decoder();
    decoder.received(stream);
    let mut lines = Vec::new();
    let mut malformed = 0usize;
    loop {
        match decoder.decode() {
            Ok(frame) => {
                let level = frame
                    .level()
                    .map(|l| l.as_str().to_uppercase())
                    .unwrap_or_else(|| "PRINT".into());
                lines.push(format!("{level:<5} {}", frame.display_message()));
            }
            Err(DecodeError::UnexpectedEof) => break,
            Err(DecodeError::Malformed) => {
                lines.push(
                    "(malformed defmt frame: the stream is damaged or the ELF does not match)"
                        .into(),
                );
                malformed += 1;
                if table.encoding().can_recover() && malformed < 16 {
                    continue;
                }
                break;
            }
        }
    }
    Ok(lines)
}
