//! `comgrasp`: the command-line front end of the engine (generate motion to a file, bench).
//!
//! It uses the Rust API (`Engine`/`Stream`) directly; the C ABI is for hosts. Arguments are
//! parsed by hand to keep the dependency set of the library crate unchanged. Every failure
//! is a message on stderr and a non-zero exit code (2: bad arguments, 1: the run failed),
//! never a panic.
mod bench;
mod body_mesh;
mod checksum;
mod generate;
mod gltf;
mod npz;
mod obj;
mod opts;
mod png;
mod preview;
mod scene;
mod shm;

use std::process::ExitCode;

const USAGE: &str = "\
comgrasp: text-driven whole-body grasp motion

usage:
  comgrasp generate [--bundle DIR] --text PROMPT [options]
                    [--out FILE.json|FILE.npz] [--glb FILE.glb] [--preview FILE.png]
  comgrasp bench [options]
  comgrasp publish --name NAME --text PROMPT [options]   (iceoryx2 shared memory)
  comgrasp subscribe --name NAME [options]
  comgrasp shm-bench [options]
  comgrasp shm-clean   reclaim shared memory that killed processes left behind
  comgrasp --help | --version

Run `comgrasp generate --help` for the generate options.";

/// Why a subcommand failed; decides the exit code.
pub enum Failure {
    /// Bad command line (exit code 2); the message says what and how to get help.
    Usage(String),
    /// The run itself failed (exit code 1).
    Run(String),
}

fn main() -> ExitCode {
    // args_os, not args: a non-UTF-8 argument must be an error message, not a panic.
    let mut args = Vec::new();
    for a in std::env::args_os().skip(1) {
        match a.into_string() {
            Ok(s) => args.push(s),
            Err(a) => return fail(Failure::Usage(format!("argument {a:?} is not valid UTF-8"))),
        }
    }
    let result = match args.first().map(String::as_str) {
        None => Err(Failure::Usage(format!("no command given\n\n{USAGE}"))),
        Some("-h" | "--help" | "help") => {
            println!("{USAGE}");
            Ok(())
        }
        Some("-V" | "--version") => {
            println!("comgrasp {} (C ABI {})", env!("CARGO_PKG_VERSION"), comgrasp::ffi::CG_ABI_VERSION);
            Ok(())
        }
        Some("generate") => generate::run(&args[1..]),
        Some("bench") => bench::run(&args[1..]).map_err(Failure::Run),
        Some("publish") => shm::publish(&args[1..]),
        Some("subscribe") => shm::subscribe(&args[1..]),
        Some("shm-bench") => shm::bench(&args[1..]),
        Some("shm-clean") => shm::clean(),
        Some(other) => Err(Failure::Usage(format!("unknown command {other:?}\n\n{USAGE}"))),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => fail(f),
    }
}

fn fail(f: Failure) -> ExitCode {
    match f {
        Failure::Usage(msg) => {
            eprintln!("comgrasp: {msg}");
            ExitCode::from(2)
        }
        Failure::Run(msg) => {
            eprintln!("comgrasp: error: {msg}");
            ExitCode::from(1)
        }
    }
}
