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
}
