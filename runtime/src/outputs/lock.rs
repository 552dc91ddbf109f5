//! One run per output folder: a run holds an advisory lock on a file in the folder for its
//! whole life, and a second run on the same folder is refused instead of overwriting the first
//! one's files. The lock is the operating system's (`flock` on Unix, `LockFileEx` on Windows):
//! it goes away with the process, also when it is killed, so a stale lock cannot block a folder.

use std::path::Path;

/// The file in an output folder that a run locks.
pub const LOCK_FILE: &str = ".softc.lock";

/// A held folder; the lock is released when this is dropped (or the process ends).
#[derive(Debug)]
pub struct FolderLock {
    _file: std::fs::File,
}

/// Create `dir` if needed and lock it for this run. `flag` names the option that chose the
/// folder in the message (`--out`).
pub fn lock_folder(dir: &Path, flag: &str) -> Result<FolderLock, String> {
    std::fs::create_dir_all(dir)
        .map_err(|e| format!("{flag} {}: cannot create the folder: {e}", dir.display()))?;
    let path = dir.join(LOCK_FILE);
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| {
            format!(
                "{flag} {}: cannot create `{}`: {e}",
                dir.display(),
                path.display()
            )
        })?;
    match file.try_lock() {
        Ok(()) => Ok(FolderLock { _file: file }),
        Err(std::fs::TryLockError::WouldBlock) => Err(format!(
            "{flag} {}: the folder is in use by another softc run (it holds a lock on `{}`); \
             wait for that run to finish, or choose another folder",
            dir.display(),
            path.display()
        )),
        Err(std::fs::TryLockError::Error(e)) => Err(format!(
            "{flag} {}: cannot lock `{}`: {e}",
            dir.display(),
            path.display()
        )),
    }
}

/// The folder, if any, that another run holds and that `path` lies in (`path` itself, or one
/// of the folders above it). A folder holds everything below it: a run writing `D/result.json`
/// or `D/vtk` while an optimization holds `D` would overwrite that run's files. Call it before
/// this run takes its own locks (a lock this process holds looks held too).
pub fn held_above(path: &Path) -> Option<std::path::PathBuf> {
    let absolute = std::path::absolute(path).ok()?;
    // The deepest folder that exists, with its links resolved as the holder's were.
    let existing = absolute.ancestors().find(|a| a.is_dir())?;
    let canonical = existing.canonicalize().ok()?;
    canonical
        .ancestors()
        .find(|a| is_held(a))
        .map(Path::to_path_buf)
}

/// Whether another open lock holds `dir`.
fn is_held(dir: &Path) -> bool {
    let Ok(file) = std::fs::File::open(dir.join(LOCK_FILE)) else {
        return false;
    };
    match file.try_lock() {
        // Released when `file` drops at the end of this function.
        Ok(()) => false,
        Err(std::fs::TryLockError::WouldBlock) => true,
        Err(std::fs::TryLockError::Error(_)) => false,
    }
}

/// Refuse outputs inside a folder another run holds: each `(flag, path)` a run will write.
pub fn check_outputs(outputs: &[(&str, &Path)]) -> Result<(), String> {
    for (flag, path) in outputs {
        if let Some(dir) = held_above(path) {
            return Err(format!(
                "{flag} {}: `{}` is in use by another softc run (it holds a lock on `{}`), \
                 and this run would overwrite its files there; wait for that run to finish, or \
                 choose a path outside that folder",
                path.display(),
                dir.display(),
                dir.join(LOCK_FILE).display()
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_a_folder_is_refused_until_the_first_is_released() {
        let d = std::env::temp_dir().join(format!("softc-lock-{}", std::process::id()));
        let first = lock_folder(&d, "--out").unwrap();
        let e = lock_folder(&d, "--out").unwrap_err();
        assert!(
            e.contains("in use by another softc run") && e.contains("--out"),
            "{e}"
        );
        drop(first);
        let again = lock_folder(&d, "--out");
        assert!(again.is_ok(), "{again:?}");
        drop(again);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_path_inside_a_held_folder_is_refused() {
        let d = std::env::temp_dir().join(format!("softc-lock-inside-{}", std::process::id()));
        let held = lock_folder(&d, "--out").unwrap();
        // Not free from inside this process either: checked before a run takes its own locks.
        for inside in [d.join("result.json"), d.join("vtk"), d.join("a/b/c.csv")] {
            let e = check_outputs(&[("--json", &inside)]).unwrap_err();
            assert!(e.contains("in use by another softc run"), "{e}");
        }
        drop(held);
        assert!(check_outputs(&[("--json", &d.join("result.json"))]).is_ok());
        assert!(held_above(&d.join("vtk")).is_none());
        std::fs::remove_dir_all(&d).unwrap();
    }
}
