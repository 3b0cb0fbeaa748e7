//! A `posefuse serve` process for the tests that need the server's own process: its CPU time,
//! its open-file limit, its log.

use std::process::Stdio;
use std::time::{Duration, Instant};

use super::model_dir;

/// A `posefuse serve` process on a free loopback port (its CPU time is its own, unlike an
/// in-process server's, which shares the test process with the other tests).
pub struct ServeProcess {
    child: std::process::Child,
    pub addr: String,
}

impl ServeProcess {
    pub fn start(env: &[(&str, String)]) -> ServeProcess {
        Self::start_with(env, &[], None)
    }

    /// With extra `serve` flags, its log (stderr) written to `log`.
    pub fn start_logging(args: &[&str], log: &std::path::Path) -> ServeProcess {
        Self::spawn(&[], args, None, std::fs::File::create(log).unwrap().into())
    }

    /// With extra `serve` flags and, when given, an open-file limit (soft and hard, so the server
    /// cannot raise it).
    pub fn start_with(env: &[(&str, String)], args: &[&str], nofile: Option<u64>) -> ServeProcess {
        Self::spawn(env, args, nofile, Stdio::null())
    }

    fn spawn(env: &[(&str, String)], args: &[&str], nofile: Option<u64>, stderr: Stdio) -> ServeProcess {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let addr = format!("127.0.0.1:{port}");
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"));
        cmd.args(["serve", "--addr", &addr, "--model-dir"]).arg(model_dir()).args(args);
        if let Some(n) = nofile {
            use std::os::unix::process::CommandExt;
            // SAFETY: setrlimit is async-signal-safe and touches only the child being started.
            unsafe {
                cmd.pre_exec(move || {
                    let lim = libc::rlimit { rlim_cur: n as libc::rlim_t, rlim_max: n as libc::rlim_t };
                    if libc::setrlimit(libc::RLIMIT_NOFILE, &lim) == 0 {
                        Ok(())
                    } else {
                        Err(std::io::Error::last_os_error())
                    }
                });
            }
        }
        cmd.env(
            "ORT_DYLIB_PATH",
            std::env::var("ORT_DYLIB_PATH").unwrap_or_else(|_| ".ort/lib/libonnxruntime.so".into()),
        );
        cmd.current_dir(env!("CARGO_MANIFEST_DIR")).stderr(stderr);
        for (k, v) in env {
            cmd.env(k, v);
        }
        let child = cmd.spawn().unwrap();
        let p = ServeProcess { child, addr };
        let t = Instant::now();
        while !p.ready() {
            assert!(t.elapsed() < Duration::from_secs(60), "not ready");
            std::thread::sleep(Duration::from_millis(50));
        }
        p
    }

    pub fn ready(&self) -> bool {
        std::net::TcpStream::connect(&self.addr).ok().is_some_and(|mut c| {
            use std::io::{Read, Write};
            let _ = c.set_read_timeout(Some(Duration::from_secs(2)));
            let _ = c.write_all(b"GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
            let mut s = String::new();
            let _ = c.read_to_string(&mut s);
            s.starts_with("HTTP/1.1 200")
        })
    }

    /// CPU seconds the process has used.
    pub fn cpu_seconds(&self) -> f64 {
        let stat = std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap();
        let fields: Vec<&str> = stat.rsplit_once(')').unwrap().1.split_whitespace().collect();
        let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
        ticks / unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// SIGTERM, as an orchestrator stops it, and its exit status (within 30 s).
    pub fn terminate(mut self) -> std::process::ExitStatus {
        // SAFETY: kill(2) on our own child's pid.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        let t = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(t.elapsed() < Duration::from_secs(30), "still running 30 s after SIGTERM");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
