//! One writer per run folder: an advisory lock on `<run>/.lock`, held while a process
//! writes into the folder (training). A second writer gets an error naming the process
//! that holds it; readers (`eval`, `render`) take no lock and keep working, as everything
//! a run writes is renamed into place whole. The lock goes with the process, however it
//! ends, so a killed run never leaves a stale lock behind.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use crate::error::{NerfError, Result};

pub const LOCK_FILE: &str = ".lock";

/// Held for as long as this value lives.
#[derive(Debug)]
pub struct RunLock {
    _file: File,
    pub path: PathBuf,
}

impl RunLock {
    /// Creates `dir` if needed and locks it, or says who holds it.
    pub fn acquire(dir: &Path) -> Result<RunLock> {
        if dir.exists() && !dir.is_dir() {
            return Err(NerfError::format(
                dir,
                "exists and is not a folder; choose another --out",
            ));
        }
        crate::io::create_dir(dir)?;
        let path = dir.join(LOCK_FILE);
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| NerfError::write(&path, e))?;
        match file.try_lock() {
            Ok(()) => {
                // Who holds it, for the message a second writer gets.
                let pid = std::process::id().to_string();
                let written = file
                    .set_len(0)
                    .and_then(|()| file.rewind())
                    .and_then(|()| file.write_all(pid.as_bytes()));
                written.map_err(|e| NerfError::write(&path, e))?;
                Ok(RunLock { _file: file, path })
            }
            Err(TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = match holder.trim() {
                    "" => "another process".to_string(),
                    pid => format!("process {pid}"),
                };
                Err(NerfError::format(
                    dir,
                    format!(
                        "is in use: {holder} is training into it (it holds {}); wait for it \\
                         to finish or stop it, or choose another --out",
                        path.display()
                    ),
                ))
            }
            // A file system without locks (some network mounts): run unlocked, as before
            // locks existed, rather than refuse to train at all.
            Err(TryLockError::Error(e)) if e.kind() == std::io::ErrorKind::Unsupported => {
                Ok(RunLock { _file: file, path })
            }
            Err(TryLockError::Error(e)) => Err(NerfError::write(&path, e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A second writer is refused with the holder named; the lock is free
    /// again once the first lets go.
    #[test]
    fn one_writer_at_a_time() {
        let dir = tempfile::tempdir().expect("tempdir");
        let run = dir.path().join("run");
        let first = RunLock::acquire(&run).expect("first lock");
        let err = RunLock::acquire(&run)
            .expect_err("second writer")
            .to_string();
        assert!(
            err.contains("in use") && err.contains(&std::process::id().to_string()),
            "{err}"
        );
        drop(first);
        RunLock::acquire(&run).expect("free again");

        let file = dir.path().join("file");
        std::fs::write(&file, "x").expect("write");
        let err = RunLock::acquire(&file).expect_err("a file").to_string();
        assert!(err.contains("not a folder"), "{err}");
    }
}
