//! `comgrasp`: the command-line front end of the engine (generate motion to a file, bench,
//! shared memory).
//!
//! Its own workspace member (cli/), so that clap, png and zip are the CLI's dependencies and
//! never the library's. It uses the Rust API (`Engine`/`Stream`) directly; the C ABI is for
//! hosts. Every failure is a message on stderr and a non-zero exit code (2: bad arguments,
//! clap's code too; 1: the run failed), never a panic.
mod bench;
mod body_mesh;
mod crowd_bench;
mod generate;
mod gltf;
mod npz;
mod png;
mod preview;
mod scene;
mod shm;

use std::process::ExitCode;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

/// comgrasp: text-driven whole-body grasp motion.
///
/// The engine's runtime options come from the COMGRASP_STEP, COMGRASP_DECODER,
/// COMGRASP_STEP_THREADS, COMGRASP_DECODER_THREADS, COMGRASP_DECODE_GROUP, COMGRASP_OVERLAP,
/// COMGRASP_NATIVE_ISA, COMGRASP_SCHEDULING and COMGRASP_SCHEDULER_THREADS environment
/// variables (docs/performance.md).
#[derive(Parser)]
#[command(name = "comgrasp", arg_required_else_help = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate one motion: a JSON or NPZ file, an animated glTF and/or a PNG strip.
    Generate(generate::Args),
    /// Measure the engine's speed on one bundle (load, text, step, decode, streams, memory).
    Bench(bench::Args),
    /// Generate while publishing every frame over iceoryx2 shared memory.
    Publish(shm::PublishArgs),
    /// Read the frames an engine publishes under a name, in another process.
    Subscribe(shm::SubscribeArgs),
    /// Measure what publishing costs (frames/s, latency, producer overhead).
    ShmBench(shm::BenchArgs),
    /// Reclaim shared memory that killed processes left behind.
    ShmClean,
}

/// Why a subcommand failed; decides the exit code.
pub enum Failure {
    /// Bad command line (exit code 2), found after parsing (e.g. a sampling value the
    /// engine refuses, an output directory that does not exist).
    Usage(String),
    /// The run itself failed (exit code 1).
    Run(String),
}

fn main() -> ExitCode {
    let version: &'static str =
        Box::leak(format!("{} (C ABI {})", env!("CARGO_PKG_VERSION"), comgrasp::ffi::CG_ABI_VERSION).into_boxed_str());
    let cli = match Cli::command().version(version).try_get_matches().and_then(|m| Cli::from_arg_matches(&m)) {
        Ok(cli) => cli,
        // --help and --version print to stdout and exit 0; errors print to stderr, exit 2.
        Err(e) => e.exit(),
    };
    let result = match cli.command {
        Command::Generate(a) => generate::run(a),
        Command::Bench(a) => bench::run(a).map_err(Failure::Run),
        Command::Publish(a) => shm::publish(a),
        Command::Subscribe(a) => shm::subscribe(a),
        Command::ShmBench(a) => shm::bench(a),
        Command::ShmClean => shm::clean(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure::Usage(msg)) => {
            eprintln!("comgrasp: {msg}");
            ExitCode::from(2)
        }
        Err(Failure::Run(msg)) => {
            eprintln!("comgrasp: error: {msg}");
            ExitCode::from(1)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_definition_is_consistent() {
        // clap's own checks: no duplicate names, valid defaults, required args reachable.
        Cli::command().debug_assert();
    }
}
