//! Child processes for crash tests: the test binary runs one of its own `#[ignore]`d tests in a
//! new process (`<test> --exact --ignored`), handing it its role in an environment variable, so
//! that a test can `kill -9` a real daemon or a real publisher without any extra binary.

use anyhow::{bail, Context, Result};
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

/// Environment variable carrying the child's arguments; unset in a normal test run.
pub const ARGS_ENV: &str = "RANGEGP_CHILD_ARGS";

/// What a child says is marked with this, so that the test harness's own output is told apart.
pub const LINE_PREFIX: &str = "@child ";

/// The arguments of this process when it runs as a child, `None` in a normal test run.
pub fn args() -> Option<String> {
    std::env::var(ARGS_ENV).ok()
}

/// Tells the parent something (`@child <what>` on stdout, flushed).
pub fn say(what: &str) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{LINE_PREFIX}{what}");
    let _ = out.flush();
}

/// How long a tool a test runs (a compiler, an interpreter, `cargo tree`) may take before the
/// test kills it and fails: generous, since CI machines are slow, but bounded.
pub const TOOL_LIMIT: Duration = Duration::from_secs(300);

/// Runs `command` to its end as [`Command::output`] does (stdin closed, stdout and stderr
/// captured), but kills it and fails when it has not ended within `timeout`.
pub fn output_within(command: &mut Command, timeout: Duration) -> Result<std::process::Output> {
    let child = command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("spawning {:?}", command.get_program()))?;
    let pid = child.id().to_string();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || tx.send(child.wait_with_output()));
    match rx.recv_timeout(timeout) {
        Ok(output) => Ok(output.context("waiting for a tool")?),
        Err(_) => {
            let _ = Command::new("kill").args(["-KILL", &pid]).status();
            bail!(
                "{:?} still running after {timeout:?}: killed",
                command.get_program()
            )
        }
    }
}

/// [`output_within`] with [`TOOL_LIMIT`], failing unless the tool succeeded (the error holds what
/// it printed): `what` names it there.
pub fn succeeded_within(command: &mut Command, what: &str) -> Result<std::process::Output> {
    let out = output_within(command, TOOL_LIMIT)?;
    anyhow::ensure!(
        out.status.success(),
        "{what} failed ({}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(out)
}

/// A child process and what it says.
pub struct ChildProcess {
    child: Child,
    lines: Receiver<String>,
}

impl ChildProcess {
    /// Runs the ignored test `test_name` of this test binary as a child with `args`.
    pub fn spawn(test_name: &str, args: &str) -> Result<Self> {
        Self::spawn_under(&[], test_name, args)
    }

    /// Like [`ChildProcess::spawn`], the test binary started by the command `wrapper` (program
    /// and arguments, the binary's path and arguments appended), e.g. `unshare --net ...`.
    pub fn spawn_under(wrapper: &[&str], test_name: &str, args: &str) -> Result<Self> {
        let exe = std::env::current_exe().context("locating the test binary")?;
        let mut command = match wrapper.split_first() {
            Some((program, rest)) => {
                let mut c = Command::new(program);
                c.args(rest).arg(exe);
                c
            }
            None => Command::new(exe),
        };
        command
            .args([
                test_name,
                "--exact",
                "--ignored",
                "--nocapture",
                "--test-threads=1",
            ])
            .env(ARGS_ENV, args);
        Self::run(command, true)
    }

    /// Runs `command` with its stdin and stdout piped: with `marked`, only the lines it says
    /// through [`say`] are heard (a test binary's own output is mixed in); without, every line.
    pub fn run(mut command: Command, marked: bool) -> Result<Self> {
        let mut child = command
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("spawning a child process")?;
        let stdout = child.stdout.take().context("child stdout")?;
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                // libtest may have written "test <name> ... " on the same line first.
                let heard = match line.find(LINE_PREFIX) {
                    Some(at) if marked => &line[at + LINE_PREFIX.len()..],
                    None if marked => continue,
                    _ => &line[..],
                };
                if tx.send(heard.to_owned()).is_err() {
                    break;
                }
            }
        });
        Ok(Self { child, lines })
    }

    /// Writes `line` to the child's stdin.
    pub fn tell(&mut self, line: &str) -> Result<()> {
        let stdin = self.child.stdin.as_mut().context("child stdin")?;
        writeln!(stdin, "{line}")?;
        stdin.flush()?;
        Ok(())
    }

    /// Closes the child's stdin: it reads end of file.
    pub fn close_input(&mut self) {
        self.child.stdin.take();
    }

    /// Waits (at most `timeout`) for the child to say a line starting with `prefix`; returns it.
    pub fn expect(&mut self, prefix: &str, timeout: Duration) -> Result<String> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) if line.starts_with(prefix) => return Ok(line),
                Ok(_) => {}
                Err(_) => {
                    let status = self.child.try_wait().ok().flatten();
                    bail!("child did not say {prefix:?} within {timeout:?} (exit status: {status:?})")
                }
            }
        }
    }

    /// Freezes the child (SIGSTOP): it keeps its sockets but reads nothing.
    pub fn stop(&self) -> Result<()> {
        let status = Command::new("kill")
            .args(["-STOP", &self.child.id().to_string()])
            .status()
            .context("running kill -STOP")?;
        anyhow::ensure!(status.success(), "kill -STOP failed: {status}");
        Ok(())
    }

    /// Waits (at most `timeout`) for the child to exit; true when it exited successfully.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<bool> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().context("waiting for the child")? {
                return Ok(status.success());
            }
            if Instant::now() > deadline {
                bail!("child still running after {timeout:?}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The child's process id.
    pub fn id(&self) -> u32 {
        self.child.id()
    }

    /// `kill -9` and reap.
    pub fn kill(mut self) -> Result<()> {
        self.child.kill().context("SIGKILL")?;
        self.child.wait().context("reaping the child")?;
        Ok(())
    }
}

impl Drop for ChildProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tool_is_heard_out_or_killed_at_its_limit() -> Result<()> {
        let out = output_within(
            Command::new("sh").args(["-c", "echo out; echo err >&2"]),
            TOOL_LIMIT,
        )?;
        assert!(out.status.success());
        assert_eq!((&out.stdout[..], &out.stderr[..]), (&b"out\n"[..], &b"err\n"[..]));
        let hung = output_within(Command::new("sleep").arg("600"), Duration::from_millis(200));
        let message = hung.expect_err("killed at its limit").to_string();
        assert!(message.contains("still running"), "{message}");
        Ok(())
    }
}
