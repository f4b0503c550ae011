//! `nephele scenes`: the built-in scenes and what each is for.

use anyhow::Result;
use nephele_pathtracer::scenes;

pub fn list() -> Result<()> {
    println!("{:<12} {:>10}  description", "name", "triangles");
    for &name in scenes::names() {
        let scene = scenes::builtin(name).map_err(|e| anyhow::anyhow!("{e}"))?;
        println!("{:<12} {:>10}  {}", scene.name, scene.scene.triangle_count(), scene.description);
    }
    Ok(())
}
