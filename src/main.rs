//! The `ptv` executable: parses the command line and hands it to [`ptv::cli`].
//!
//! Exit codes: 0 on success, 1 when the command fails (one line `error: ...`
//! on standard error), 2 for usage errors (clap's own message).

use std::io::{self, Write};
use std::process::ExitCode;

use clap::Parser;
use ptv::cli::{Cli, Command};

fn main() -> ExitCode {
    // No subcommand: the service, as `ptv serve` (its flags from the
    // environment, if set there).
    let command = match Cli::parse().command {
        Some(command) => command,
        None => match Cli::parse_from(["ptv", "serve"]).command {
            Some(command) => command,
            None => return ExitCode::FAILURE,
        },
    };
    let result = match command {
        // The service's and the worker's threads log to standard error, and
        // `ptv upload`'s runtime threads draw its progress bar there: no
        // locks held here.
        unlocked @ (Command::Serve(_) | Command::Worker(_) | Command::Upload(_)) => {
            ptv::cli::run(unlocked, &mut io::stdout(), &mut io::stderr())
        }
        other => ptv::cli::run(other, &mut io::stdout().lock(), &mut io::stderr().lock()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            let _ = writeln!(
                io::stderr(),
                "error: {}",
                one_line(&anyhow::Error::from(error))
            );
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes as one line, joined with `: `.
///
/// A cause whose message the error already ends with is written only once.
fn one_line(error: &anyhow::Error) -> String {
    let mut message = String::new();
    for cause in error.chain() {
        let text = cause.to_string();
        if message.ends_with(&text) {
            continue;
        }
        if !message.is_empty() {
            message.push_str(": ");
        }
        message.push_str(&text);
    }
    message.replace(['\r', '\n'], " ")
}
