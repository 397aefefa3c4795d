//! A real PostgreSQL for the service tests: with `PTV_TEST_DATABASE=postgres`
//! every server the tests start (in this process, and `ptv serve` and
//! `ptv worker` child processes) runs against a fresh database on one
//! PostgreSQL server per test process, started from the system's binaries
//! (`initdb` and `pg_ctl`, found on `PATH` or under
//! `/usr/lib/postgresql/*/bin`) in `target/tmp/postgres-PID` on a free
//! port, with `fsync = off` (the tests do not cut the power) and trust
//! authentication on 127.0.0.1. Unset, the tests use SQLite as before.
//!
//! PostgreSQL refuses to run as root: as root, the server runs as `nobody`
//! (`runuser`), in a data directory it owns. A watchdog shell waits for
//! the test process to end (however it ends, `kill -9` included) and then
//! stops the server and removes its directory; a server whose test
//! process and watchdog are both gone is stopped at the next start.
//!
//! A data directory stands for its database: the first server started on
//! a data directory creates one (`CREATE DATABASE`), and every later
//! server on the same directory (a restart, a `ptv worker` beside a `ptv
//! serve`) gets the same one.

use std::collections::HashMap;
use std::fs::File;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Mutex, OnceLock};

/// Whether the tests run against PostgreSQL (`PTV_TEST_DATABASE=postgres`).
pub fn enabled() -> bool {
    std::env::var("PTV_TEST_DATABASE").is_ok_and(|v| v == "postgres")
}

/// The user the server runs as when the tests run as root.
const UNPRIVILEGED: (&str, u32) = ("nobody", 65534);

/// A PostgreSQL server of the tests.
pub struct Server {
    /// The directory of `initdb`, `pg_ctl`, `psql`.
    bin: PathBuf,
    /// Its data directory.
    data: PathBuf,
    /// Its port on 127.0.0.1.
    pub port: u16,
    /// Whether it runs as [`UNPRIVILEGED`] (the tests run as root).
    as_nobody: bool,
}

static SHARED: OnceLock<Server> = OnceLock::new();
static DATABASES: Mutex<Option<HashMap<PathBuf, String>>> = Mutex::new(None);
static NEXT: AtomicU32 = AtomicU32::new(0);

/// The database URL of the servers started on `data_dir`: `None` on
/// SQLite; under PostgreSQL a database of the shared server, created at
/// the first call for this directory.
pub fn database_url(data_dir: &Path) -> Option<String> {
    if !enabled() {
        return None;
    }
    let server = SHARED.get_or_init(|| Server::start("shared"));
    let mut databases = DATABASES.lock().unwrap_or_else(|e| e.into_inner());
    let databases = databases.get_or_insert_with(HashMap::new);
    if let Some(url) = databases.get(data_dir) {
        return Some(url.clone());
    }
    let url = server.create_database();
    databases.insert(data_dir.to_owned(), url.clone());
    Some(url)
}

impl Server {
    /// Initialises and starts a server of its own (`name` tells its
    /// directory apart), on a free port.
    pub fn start(name: &str) -> Server {
        let bin = binaries();
        let base = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
        std::fs::create_dir_all(&base).unwrap();
        stop_stale(&bin, &base);
        let as_nobody = rustix::process::geteuid().is_root();
        let data = base.join(format!("postgres-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&data);
        std::fs::create_dir_all(&data).unwrap();
        if as_nobody {
            std::os::unix::fs::chown(&data, Some(UNPRIVILEGED.1), Some(UNPRIVILEGED.1)).unwrap();
        }
        let server = Server {
            bin,
            data,
            port: free_port(),
            as_nobody,
        };
        let cluster = server.data.join("cluster");
        server.run(
            "initdb",
            &[
                "-D".as_ref(),
                cluster.as_os_str(),
                "-U".as_ref(),
                "postgres".as_ref(),
                "--auth=trust".as_ref(),
                "-E".as_ref(),
                "UTF8".as_ref(),
                "--no-sync".as_ref(),
                "--no-instructions".as_ref(),
            ],
        );
        server.watch();
        server.start_again();
        server
    }

    /// Starts the (stopped) server again on its port.
    pub fn start_again(&self) {
        let cluster = self.data.join("cluster");
        let options = format!(
            "-p {} -k {} -c listen_addresses=127.0.0.1 -c fsync=off \
             -c synchronous_commit=off -c full_page_writes=off -c max_connections=400",
            self.port,
            self.data.display()
        );
        self.run(
            "pg_ctl",
            &[
                "-D".as_ref(),
                cluster.as_os_str(),
                "-l".as_ref(),
                self.data.join("server.log").as_os_str(),
                "-w".as_ref(),
                "-t".as_ref(),
                "60".as_ref(),
                "-o".as_ref(),
                options.as_ref(),
                "start".as_ref(),
            ],
        );
    }

    /// Stops the server (`pg_ctl stop -m fast`: sessions are disconnected).
    pub fn stop(&self) {
        let cluster = self.data.join("cluster");
        self.run(
            "pg_ctl",
            &[
                "-D".as_ref(),
                cluster.as_os_str(),
                "-w".as_ref(),
                "-m".as_ref(),
                "fast".as_ref(),
                "stop".as_ref(),
            ],
        );
    }

    /// A new database; its URL.
    pub fn create_database(&self) -> String {
        let name = format!("ptv_test_{}", NEXT.fetch_add(1, Ordering::Relaxed));
        let output = Command::new(self.bin.join("psql"))
            .args(["-h", "127.0.0.1", "-U", "postgres", "-d", "postgres", "-q"])
            .args(["-v", "ON_ERROR_STOP=1", "-p"])
            .arg(self.port.to_string())
            .arg("-c")
            .arg(format!("CREATE DATABASE {name}"))
            .stdin(Stdio::null())
            .output()
            .expect("psql runs");
        assert!(
            output.status.success(),
            "CREATE DATABASE failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
        format!("postgres://postgres@127.0.0.1:{}/{name}", self.port)
    }

    /// Runs one of the server's programs (as [`UNPRIVILEGED`] when the
    /// tests run as root), its output in the data directory's
    /// `commands.log` (a file, not a pipe: the server it starts keeps its
    /// descriptors); panics with that log when it fails.
    fn run(&self, program: &str, args: &[&std::ffi::OsStr]) {
        let log_path = self.data.join("commands.log");
        let log = File::options()
            .create(true)
            .append(true)
            .open(&log_path)
            .unwrap();
        let mut command = if self.as_nobody {
            let mut c = Command::new("runuser");
            c.args(["-u", UNPRIVILEGED.0, "--"])
                .arg(self.bin.join(program));
            c
        } else {
            Command::new(self.bin.join(program))
        };
        let status = command
            .args(args)
            .current_dir(&self.data)
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .status()
            .unwrap_or_else(|e| panic!("{program} does not start: {e}"));
        assert!(
            status.success(),
            "{program} failed: {}",
            std::fs::read_to_string(&log_path).unwrap_or_default()
        );
    }

    /// Starts the watchdog: a shell that waits for this test process to
    /// end, then stops the server and removes its directory.
    fn watch(&self) {
        let stop = self.stop_command();
        let script = format!(
            "while kill -0 {pid} 2>/dev/null; do sleep 1; done; {stop}; rm -rf '{data}'",
            pid = std::process::id(),
            data = self.data.display(),
        );
        // Started in the background of a shell that exits at once: the
        // watchdog is nobody's child here, and outlives this process.
        let status = Command::new("sh")
            .args(["-c", &format!("({script}) >/dev/null 2>&1 &")])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .expect("sh starts");
        assert!(status.success(), "the watchdog did not start");
    }

    /// The shell command that stops the server at once.
    fn stop_command(&self) -> String {
        stop_command(&self.bin, &self.data.join("cluster"), self.as_nobody)
    }
}

/// `pg_ctl stop -m immediate` of the cluster in `cluster`, as a shell
/// command.
fn stop_command(bin: &Path, cluster: &Path, as_nobody: bool) -> String {
    let user = if as_nobody {
        format!("runuser -u {} -- ", UNPRIVILEGED.0)
    } else {
        String::new()
    };
    format!(
        "{user}'{}' -D '{}' -m immediate stop >/dev/null 2>&1",
        bin.join("pg_ctl").display(),
        cluster.display()
    )
}

/// Stops and removes the servers of test processes that are gone (their
/// watchdog was killed too).
fn stop_stale(bin: &Path, base: &Path) {
    let Ok(entries) = std::fs::read_dir(base) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = name
            .strip_prefix("postgres-")
            .and_then(|rest| rest.split('-').next())
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if pid == std::process::id() || Path::new(&format!("/proc/{pid}")).exists() {
            continue;
        }
        let as_nobody = rustix::process::geteuid().is_root();
        let _ = Command::new("sh")
            .args([
                "-c",
                &stop_command(bin, &entry.path().join("cluster"), as_nobody),
            ])
            .status();
        let _ = std::fs::remove_dir_all(entry.path());
    }
}

/// The directory of PostgreSQL's programs: `initdb`'s on `PATH` (links
/// followed), else the newest `/usr/lib/postgresql/*/bin`.
fn binaries() -> PathBuf {
    let on_path = std::env::var_os("PATH").and_then(|path| {
        std::env::split_paths(&path)
            .map(|dir| dir.join("initdb"))
            .find(|initdb| initdb.is_file())
            .and_then(|initdb| std::fs::canonicalize(initdb).ok())
            .and_then(|initdb| initdb.parent().map(Path::to_owned))
    });
    if let Some(dir) = on_path {
        return dir;
    }
    let mut versions: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .map(|entry| entry.path().join("bin"))
        .filter(|bin| bin.join("initdb").is_file())
        .collect();
    versions.sort_by_key(|bin| {
        bin.parent()
            .and_then(|v| v.file_name())
            .and_then(|v| v.to_str())
            .and_then(|v| v.parse::<u32>().ok())
            .unwrap_or(0)
    });
    versions.pop().expect(
        "PTV_TEST_DATABASE=postgres needs PostgreSQL's initdb and pg_ctl \
         (on PATH or under /usr/lib/postgresql/*/bin; apt-get install postgresql)",
    )
}

/// A port free on 127.0.0.1 now.
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}
