//! What the system says about processes: this host's name, whether a
//! process still runs, this process's resident memory, how a shell runs
//! this program again, and its executable's bytes and stamp (what
//! identifies a build to the bake cache).

use crate::error::{Error, Result};
use std::ffi::OsStr;
use std::io::Read as _;
use std::path::{Path, PathBuf};
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

/// How a shell runs this program again, for the commands it suggests.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Invocation {
    /// `PATH` finds this very program under its name.
    OnPath(String),
    /// A cargo build (it lies in a profile folder of a `target` folder):
    /// `cargo run --release --` from the checkout.
    Cargo,
    /// Neither: its full path.
    Path(PathBuf),
}

impl Invocation {
    /// How to run this program, known to users as `name`.
    pub fn of_this_program(name: &str) -> Invocation {
        match std::env::current_exe() {
            Ok(exe) => Invocation::find(name, &exe, std::env::var_os("PATH").as_deref()),
            Err(_) => Invocation::OnPath(name.to_string()),
        }
    }

    /// How to run the program `exe` given the search path `path_var`: its
    /// `name` when a folder of the path holds `name` leading to `exe`
    /// itself (another program of that name does not count).
    fn find(name: &str, exe: &Path, path_var: Option<&OsStr>) -> Invocation {
        let exe = std::fs::canonicalize(exe).unwrap_or_else(|_| exe.to_path_buf());
        let on_path = path_var
            .into_iter()
            .flat_map(std::env::split_paths)
            .any(|dir| std::fs::canonicalize(dir.join(name)).is_ok_and(|found| found == exe));
        if on_path {
            return Invocation::OnPath(name.to_string());
        }
        // `target/PROFILE/NAME` or `target/TRIPLE/PROFILE/NAME`.
        let in_target = [2, 3]
            .into_iter()
            .any(|up| exe.ancestors().nth(up).and_then(Path::file_name) == Some("target".as_ref()));
        if in_target {
            Invocation::Cargo
        } else {
            Invocation::Path(exe)
        }
    }

    /// The words a shell runs the program with, before its arguments.
    pub fn command(&self) -> String {
        match self {
            Invocation::OnPath(name) => name.clone(),
            Invocation::Cargo => "cargo run --release --".to_string(),
            Invocation::Path(path) => {
                let path = path.display().to_string();
                let plain = |c: char| c.is_ascii_alphanumeric() || "/._-+,:@%".contains(c);
                if path.chars().all(plain) {
                    path
                } else {
                    format!("'{}'", path.replace('\'', "'\\''"))
                }
            }
        }
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
/// whether it changed since its hash was recorded; `None` where that
/// cannot be read.
pub fn own_executable_stamp() -> Option<super::Stamp> {
    super::stamp(&std::env::current_exe().ok()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(unix)]
    #[test]
    fn a_program_is_run_by_name_from_path_through_cargo_or_by_its_path() {
        let dir = tempfile::tempdir().unwrap();
        let root = std::fs::canonicalize(dir.path()).unwrap();
        let exe = root.join("target/release/tool");
        let other = root.join("elsewhere/tool");
        for file in [&exe, &other] {
            crate::files::write_atomic(file, b"").unwrap();
        }
        std::fs::create_dir(root.join("bin")).unwrap();
        std::os::unix::fs::symlink(&exe, root.join("bin/tool")).unwrap();
        let search =
            |dirs: &[&str]| std::env::join_paths(dirs.iter().map(|d| root.join(d))).unwrap();
        let find = |exe: &Path, dirs: &[&str]| Invocation::find("tool", exe, Some(&search(dirs)));
        assert_eq!(
            find(&exe, &["none", "bin"]),
            Invocation::OnPath("tool".into())
        );
        assert_eq!(find(&exe, &["elsewhere"]), Invocation::Cargo);
        assert_eq!(Invocation::find("tool", &exe, None), Invocation::Cargo);
        assert_eq!(find(&other, &["bin"]), Invocation::Path(other.clone()));
        let triple = root.join("target/x86_64-unknown-linux-gnu/debug/tool");
        crate::files::write_atomic(&triple, b"").unwrap();
        assert_eq!(find(&triple, &[]), Invocation::Cargo);
        assert_eq!(Invocation::OnPath("tool".into()).command(), "tool");
        assert_eq!(Invocation::Cargo.command(), "cargo run --release --");
        assert_eq!(
            Invocation::Path("/opt/my tools/it's".into()).command(),
            "'/opt/my tools/it'\\''s'"
        );
    }

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
