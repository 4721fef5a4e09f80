use anyhow::Result;
use std::path::PathBuf;
fn main() -> Result<()> {
    let dir = PathBuf::from(std::env::args().nth(1).unwrap());
    let t = exporter::pfnn_dir::load_pfnn_dir(&dir)?;
    let a = host_sim::accuracy::measure(&t, 64, 7)?;
    println!("{}", a.table());
    println!("{}", serde_json::to_string_pretty(&a.int8_report.layers)?);
    for r in &a.rows { println!("spread {}\n{}", r.spread, r.int8.table()); }
    Ok(())
}
