//! What the system says about processes: this host's name, whether a
//! process still runs, and this process's resident memory.

use crate::error::{Error, Result};
use std::io::Read as _;
use std::path::Path;
use std::sync::OnceLock;

/// This machine's name as it appears in temporary file names: the host
/// name with anything but letters, digits, `.`, `-` and `_` replaced by
/// `_` (`unknown` when it cannot be read).
pub fn host_name() -> &'static str {
    static NAME: OnceLock<String> = OnceLock::new();
    NAME.get_or_init(|| {
        let name: String = raw_host_name()
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        if name.is_empty() {
            "unknown".into()
        } else {
            name
        }
    })
}

#[cfg(unix)]
fn raw_host_name() -> String {
    let mut buffer = [0u8; 256];
    // SAFETY: the buffer is writable for its whole length; gethostname
    // writes at most that many bytes.
    let status = unsafe { libc::gethostname(buffer.as_mut_ptr().cast(), buffer.len()) };
    if status != 0 {
        return String::new();
    }
    let end = buffer.iter().position(|&b| b == 0).unwrap_or(buffer.len());
    String::from_utf8_lossy(&buffer[..end]).into_owned()
}

#[cfg(not(unix))]
fn raw_host_name() -> String {
    std::env::var("COMPUTERNAME").unwrap_or_default()
}

/// Whether process `pid` still runs (Linux: `/proc`; elsewhere assumed
/// not, so its temporary files count as stale).
pub(super) fn process_alive(pid: u32) -> bool {
    cfg!(target_os = "linux") && Path::new("/proc").join(pid.to_string()).exists()
}

/// This process's resident memory in bytes, now and at its peak.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ResidentMemory {
    pub resident: u64,
    pub peak: u64,
}

/// This process's resident memory (Linux `/proc/self/status`), or zeros
/// where unknown.
pub fn resident_memory() -> ResidentMemory {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return ResidentMemory::default();
    };
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|rest| rest.trim().strip_suffix("kB"))
            .and_then(|kb| kb.trim().parse::<u64>().ok())
            .map_or(0, |kb| kb * 1024)
    };
    ResidentMemory {
        resident: field("VmRSS:"),
        peak: field("VmHWM:"),
    }
}

/// Hands the bytes of this process's own executable to `each`, a piece at
/// a time (what identifies the build: the bake cache keys its results
/// under its hash, so another build never reuses them).
pub fn read_own_executable(each: &mut dyn FnMut(&[u8])) -> Result<()> {
    let path = std::env::current_exe()
        .map_err(|e| Error::io(Path::new("shadowcull"), "find the running executable", e))?;
    let mut file = std::fs::File::open(&path)
        .map_err(|e| Error::io(&path, "read the running executable", e))?;
    let mut buffer = vec![0u8; 1 << 20];
    loop {
        let n = file
            .read(&mut buffer)
            .map_err(|e| Error::io(&path, "read the running executable", e))?;
        if n == 0 {
            return Ok(());
        }
        each(&buffer[..n]);
    }
}

/// What the file system says of this process's executable, to tell
/// whether it changed since its hash was recorded: its length, inode and
/// device, and its modification and status-change times (nanoseconds
/// since the epoch); `None` where those cannot be read.
pub fn own_executable_stamp() -> Option<[u64; 5]> {
    let path = std::env::current_exe().ok()?;
    let meta = std::fs::metadata(path).ok()?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let ns = |s: i64, n: i64| {
            (s as u64)
                .wrapping_mul(1_000_000_000)
                .wrapping_add(n as u64)
        };
        Some([
            meta.len(),
            meta.ino(),
            meta.dev(),
            ns(meta.mtime(), meta.mtime_nsec()),
            ns(meta.ctime(), meta.ctime_nsec()),
        ])
    }
    #[cfg(not(unix))]
    {
        let _ = meta;
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn host_names_are_file_name_safe() {
        let host = host_name();
        assert!(!host.is_empty());
        assert!(host
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_')));
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn resident_memory_is_read_and_the_peak_is_at_least_the_present() {
        let memory = resident_memory();
        assert!(memory.resident > 0, "{memory:?}");
        assert!(memory.peak >= memory.resident, "{memory:?}");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn this_process_runs_and_one_above_the_largest_id_does_not() {
        assert!(process_alive(std::process::id()));
        // Linux process ids stay below 2^22 (`pid_max`'s ceiling).
        assert!(!process_alive(1 << 22 | 1));
    }
}
