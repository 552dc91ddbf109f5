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

/// Whether `path` can be written as a file later ([`write_atomically`]): checked before a run
/// so its results are not lost at the end. Names the problem and the way out; creates nothing.
pub fn check_writable_file(path: &Path) -> Result<(), String> {
    let target = link_target(path).map_err(|e| e.to_string())?;
    if target.is_dir() {
        return Err(format!(
            "`{}` is a folder; give the path of a file in it",
            path.display()
        ));
    }
    let dir = target
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(format!(
            "the folder `{}` does not exist; create it or write elsewhere",
            dir.display()
        ));
    }
    probe(dir)
}

/// Whether files can be written into the folder `dir` later: an existing folder must be
/// writable, a missing one creatable (its nearest existing ancestor a writable folder). Creates
/// nothing.
pub fn check_writable_dir(dir: &Path) -> Result<(), String> {
    let mut existing = dir;
    loop {
        match std::fs::metadata(existing) {
            Ok(m) if m.is_dir() => break,
            Ok(_) => {
                return Err(if existing == dir {
                    format!("`{}` is a file, not a folder", dir.display())
                } else {
                    format!(
                        "`{}` cannot be created: `{}` is a file, not a folder",
                        dir.display(),
                        existing.display()
                    )
                });
            }
            Err(_) => match existing.parent() {
                Some(p) if !p.as_os_str().is_empty() => existing = p,
                _ => {
                    existing = Path::new(".");
                    break;
                }
            },
        }
    }
    probe(existing).map_err(|e| {
        if existing == dir {
            e
        } else {
            format!("`{}` cannot be created: {e}", dir.display())
        }
    })
}

/// Create (and remove) a file in `dir`: the one reliable test of write permission (access
/// bits do not tell of read-only mounts, ACLs or root).
fn probe(dir: &Path) -> Result<(), String> {
    // A name no other probe uses at the same time: several probes may run in one process
    // (commands run in-process, on threads), and a killed run may have left one behind.
    static PROBES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let mut last = None;
    for _ in 0..8 {
        let n = PROBES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = dir.join(format!(".softc-write-test.{}.{n}.tmp", std::process::id()));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(_) => {
                let _ = std::fs::remove_file(&tmp);
                return Ok(());
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => return Err(format!("cannot write into `{}`: {e}", dir.display())),
        }
    }
    Err(format!(
        "cannot write into `{}`: {}",
        dir.display(),
        last.map_or_else(String::new, |e| e.to_string())
    ))
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

    #[test]
    fn outputs_are_checked_before_the_work() {
        let d = scratch("check");
        let file = d.join("f.json");
        std::fs::write(&file, "x").unwrap();
        assert!(check_writable_file(&file).is_ok());
        assert!(check_writable_file(&d.join("new.json")).is_ok());
        let e = check_writable_file(&d).unwrap_err();
        assert!(e.contains("is a folder"), "{e}");
        let e = check_writable_file(&d.join("missing/x.json")).unwrap_err();
        assert!(e.contains("does not exist"), "{e}");
        assert!(check_writable_dir(&d).is_ok());
        assert!(check_writable_dir(&d.join("a/b/c")).is_ok());
        assert!(!d.join("a").exists(), "nothing is created");
        let e = check_writable_dir(&file).unwrap_err();
        assert!(e.contains("is a file, not a folder"), "{e}");
        let e = check_writable_dir(&file.join("sub")).unwrap_err();
        assert!(e.contains("is a file, not a folder"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }
}
