//! Files replaced whole or not at all: a write goes to a temporary file beside the target,
//! then a rename puts it in place.

use std::io::Write;
use std::path::{Path, PathBuf};

/// The file a write to `path` replaces: `path`, or where the chain of symbolic links at `path`
/// ends (which need not exist yet).
fn link_target(path: &Path) -> std::io::Result<PathBuf> {
    let mut p = path.to_path_buf();
    // The kernel's own limit on a chain of links (ELOOP beyond it).
    for _ in 0..40 {
        match std::fs::symlink_metadata(&p) {
            Ok(m) if m.file_type().is_symlink() => {
                let to = std::fs::read_link(&p)?;
                p = match p.parent() {
                    Some(dir) if to.is_relative() => dir.join(to),
                    _ => to,
                };
            }
            _ => return Ok(p),
        }
    }
    Err(std::io::Error::other(format!(
        "`{}`: too many levels of symbolic links",
        path.display()
    )))
}

/// Replace `path` with `bytes` through a temporary file in the same directory and a rename, so
/// an interrupted write never leaves a truncated file. A symbolic link is written through: its
/// target is replaced and the link stays a link (renaming onto the link would replace the link
/// with a file and leave the target as it was).
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let target = link_target(path)?;
    let path = target.as_path();
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let tmp = dir.join(format!(".{file_name}.{}.tmp", std::process::id()));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        if let Ok(meta) = std::fs::metadata(path) {
            let _ = std::fs::set_permissions(&tmp, meta.permissions());
        }
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("softc-atomic-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// Issue 20 item 7: writing through a link replaced the link with a file.
    #[test]
    fn a_write_through_a_symbolic_link_replaces_its_target_and_keeps_the_link() {
        let d = scratch("link");
        std::fs::create_dir_all(d.join("real")).unwrap();
        let target = d.join("real/script.soft");
        std::fs::write(&target, "old").unwrap();
        // A relative link, and a link to that link.
        std::os::unix::fs::symlink("real/script.soft", d.join("link.soft")).unwrap();
        std::os::unix::fs::symlink(d.join("link.soft"), d.join("link2.soft")).unwrap();
        write_atomically(&d.join("link2.soft"), b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "new");
        for l in ["link.soft", "link2.soft"] {
            let m = std::fs::symlink_metadata(d.join(l)).unwrap();
            assert!(m.file_type().is_symlink(), "{l} is still a link");
        }
        // A dangling link: its target is created.
        std::os::unix::fs::symlink("real/new.json", d.join("dangling.json")).unwrap();
        write_atomically(&d.join("dangling.json"), b"{}").unwrap();
        assert_eq!(
            std::fs::read_to_string(d.join("real/new.json")).unwrap(),
            "{}"
        );
        // A cycle is an error, not a loop.
        std::os::unix::fs::symlink("b", d.join("a")).unwrap();
        std::os::unix::fs::symlink("a", d.join("b")).unwrap();
        let e = write_atomically(&d.join("a"), b"x").unwrap_err();
        assert!(e.to_string().contains("symbolic links"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }
}
