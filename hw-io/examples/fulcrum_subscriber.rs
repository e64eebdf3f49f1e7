//! A guidance-force module's side of comanip, as user code: read fulcrumd's fulcrum estimate
//! from shared memory and act only on valid samples.
//!
//! ```sh
//! cargo run --release --bin fulcrumd &                      # the daemon on its simulated robot
//! cargo run --release -p hw-io --example fulcrum_subscriber  # this subscriber
//! cargo run --release -p hw-io --example fulcrum_subscriber -- comanip/fulcrum 5000
//! ```
//!
//! Arguments: the output service name (`[output] service` of fulcrumd's config, default
//! `comanip/fulcrum`) and, optionally, how many samples to read before exiting. Frames and
//! units are those of `docs/output.md`: the fulcrum in metres, robot base frame.

use std::process::ExitCode;
use std::time::Duration;

use hw_io::ipc::{Continuity, FulcrumSubscriber, OutputState};

fn run(service: &str, samples: Option<u64>) -> Result<(), Box<dyn std::error::Error>> {
    let mut sub = FulcrumSubscriber::connect(service)?;
    eprintln!("listening on {service:?}");
    let mut last_state = None;
    let mut read = 0u64;
    while samples.is_none_or(|n| read < n) {
        // Block until a sample arrives (no busy-polling), at most 100 ms.
        let Some(r) = sub.wait(Duration::from_millis(100))? else {
            eprintln!("no sample for 100 ms: is fulcrumd running?");
            continue;
        };
        read += 1;
        match r.event {
            Continuity::Restart => eprintln!("fulcrumd restarted: estimates start afresh"),
            Continuity::Gap { missed } => eprintln!("{missed} samples missed (reading too slowly?)"),
            Continuity::First | Continuity::InOrder => {}
        }
        let s = r.sample;
        // Never use an invalid sample: its health flags say why (docs/output.md). A state this
        // program does not know (a newer daemon) is treated as invalid too.
        let state = match s.state() {
            Ok(OutputState::Invalid) => continue,
            Ok(state) => state,
            Err(unknown) => {
                eprintln!("cycle {}: {unknown}: ignored", s.sequence);
                continue;
            }
        };
        if last_state != Some((state, s.trocar_id)) {
            match (state, s.fulcrum()) {
                (OutputState::Inside, Some(f)) => println!(
                    "cycle {}: inside trocar #{}, fulcrum ({:+.4}, {:+.4}, {:+.4}) m, robot base frame",
                    s.sequence, s.trocar_id, f[0], f[1], f[2]
                ),
                _ => println!("cycle {}: outside: no fulcrum to guide to", s.sequence),
            }
            last_state = Some((state, s.trocar_id));
        }
    }
    let c = sub.counters();
    eprintln!("received {}, missed {}, restarts {}, refused {}", c.received, c.missed, c.restarts, c.rejected);
    Ok(())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let service = args.next().unwrap_or_else(|| "comanip/fulcrum".to_string());
    let samples = match args.next().map(|a| a.parse::<u64>()) {
        None => None,
        Some(Ok(n)) => Some(n),
        Some(Err(e)) => {
            eprintln!("fulcrum_subscriber: the sample count must be a number: {e}");
            return ExitCode::FAILURE;
        }
    };
    match run(&service, samples) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fulcrum_subscriber: {e}");
            ExitCode::FAILURE
        }
    }
}
