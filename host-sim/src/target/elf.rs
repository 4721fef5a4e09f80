//! What host-sim reads from the firmware ELF: section sizes (flash and RAM
//! use) and the region addresses memory.x exports as symbols.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{anyhow, Context, Result};
use object::{Object, ObjectSection, ObjectSymbol};

/// Section sizes and region bounds of a firmware image.
#[derive(Clone, Debug)]
pub struct ElfInfo {
    /// Size in bytes of every allocated section, by name.
    pub sections: BTreeMap<String, u64>,
    /// MODEL region `[start, end)` (memory.x).
    pub model: (u64, u64),
    /// STYLES region `[start, end)` (memory.x).
    pub styles: (u64, u64),
    /// HOSTIO region `[start, end)` (memory.x).
    pub hostio: (u64, u64),
    /// BIGMODEL region `[start, end)` (memory.x): blobs too large for
    /// MODEL; `None` in firmwares linked before it existed.
    pub bigmodel: Option<(u64, u64)>,
    /// The ELF's bytes (defmt reads its string table from them).
    pub bytes: Vec<u8>,
}

impl ElfInfo {
    /// Reads `path`.
    pub fn read(path: &Path) -> Result<ElfInfo> {
        let bytes = std::fs::read(path)
            .with_context(|| format!("cannot read firmware {}", path.display()))?;
        let file = object::File::parse(&*bytes)
            .with_context(|| format!("{} is not an ELF file", path.display()))?;
        let mut sections = BTreeMap::new();
        for s in file.sections() {
            if let Ok(name) = s.name() {
                if s.address() != 0 || name.starts_with(".vector_table") {
                    sections.insert(name.to_string(), s.size());
                }
            }
        }
        let symbol = |name: &str| -> Result<u64> {
            file.symbols()
                .find(|s| s.name() == Ok(name))
                .map(|s| s.address())
                .ok_or_else(|| {
                    anyhow!(
                        "{}: symbol {name} missing (is memory.x the phasegate one?)",
                        path.display()
                    )
                })
        };
        let model = (
            symbol("_phasegate_model_start")?,
            symbol("_phasegate_model_end")?,
        );
        let styles = (
            symbol("_phasegate_styles_start")?,
            symbol("_phasegate_styles_end")?,
        );
        let hostio = (
            symbol("_phasegate_hostio_start")?,
            symbol("_phasegate_hostio_end")?,
        );
        let bigmodel = symbol("_phasegate_bigmodel_start")
            .and_then(|s| Ok((s, symbol("_phasegate_bigmodel_end")?)))
            .ok();
        Ok(ElfInfo {
            sections,
            model,
            styles,
            hostio,
            bigmodel,
            bytes,
        })
    }

    /// Size of a section, 0 when absent.
    pub fn size(&self, name: &str) -> u64 {
        self.sections.get(name).copied().unwrap_or(0)
    }
}
