//! The `ptv` executable: parses the command line and hands it to [`ptv::cli`].
//!
//! Exit codes: 0 on success, 1 when the command fails (one line `error: ...`
//! on standard error), 2 for usage errors (clap's own message).

use std::io::{self, Write};
use std::process::ExitCode;

use clap::{CommandFactory, Parser};
use ptv::cli::Cli;

fn main() -> ExitCode {
    let cli = Cli::parse();
    let Some(command) = cli.command else {
        // No subcommand: print the help. This is where the HTTP service will
        // start once it exists.
        let _ = Cli::command()
            .print_help()
            .and_then(|()| writeln!(io::stdout()));
        return ExitCode::SUCCESS;
    };
    let result = ptv::cli::run(command, &mut io::stdout().lock(), &mut io::stderr().lock());
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
