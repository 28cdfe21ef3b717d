//! Frames across processes through iceoryx2: the producer is `comgrasp publish` (an engine
//! on the tiny bundle that publishes while it polls, writing the bytes of every frame its
//! `poll` returned), the consumers are `examples_c/subscribe.c` (the C ABI's
//! `cg_subscriber_*`, compiled here), each in its own process.
#![cfg(unix)]

#[path = "../../tests/host_support/mod.rs"]
mod host_support;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use host_support::*;

const FRAME_BYTES: usize = 1608;
const PROMPT: &str = "A man lifts the small cube with his left hand";
/// A host that polls one frame per 5 ms tick through a 4-frame ring: the producer's
/// worker is held back by the host, so a stream lasts long enough to act during it.
const PACED: &[&str] = &["--wait-subscribers", "1", "--poll-interval-ms", "5", "--ring", "4"];

fn c_subscriber() -> &'static Path {
    static EXE: OnceLock<PathBuf> = OnceLock::new();
    EXE.get_or_init(|| compile("CC", "cc", "-std=c11", &["examples_c/subscribe.c"], "shm_ipc_subscribe", &[]))
}

/// A child process whose stdout lines arrive on a channel.
struct Proc {
    child: Child,
    lines: Receiver<String>,
    seen: Vec<String>,
    what: String,
}

impl Proc {
    fn spawn(cmd: &mut Command) -> Proc {
        let what = format!("{cmd:?}");
        let mut child =
            cmd.stdin(Stdio::null()).stdout(Stdio::piped()).spawn().unwrap_or_else(|e| panic!("{what}: {e}"));
        let (tx, lines) = channel();
        let out = BufReader::new(child.stdout.take().unwrap());
        std::thread::spawn(move || {
            for l in out.lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        Proc { child, lines, seen: Vec::new(), what }
    }

    /// Waits for a line starting with `prefix`.
    fn wait_for(&mut self, prefix: &str, limit: Duration) {
        let t0 = Instant::now();
        while t0.elapsed() < limit {
            if let Ok(l) = self.lines.recv_timeout(Duration::from_millis(50)) {
                let hit = l.starts_with(prefix);
                self.seen.push(l);
                if hit {
                    return;
                }
            }
        }
        let _ = self.child.kill();
        panic!("{}: no {prefix:?} line within {limit:?}; got {:?}", self.what, self.seen);
    }

    /// Waits for the exit (killing it after `limit`), asserts success, returns all stdout.
    fn finish(mut self, limit: Duration) -> String {
        let t0 = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            if t0.elapsed() > limit {
                let _ = self.child.kill();
                panic!("{} did not finish within {limit:?}; stdout so far {:?}", self.what, self.seen);
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        // The reader thread ends at EOF; collect what it still has.
        while let Ok(l) = self.lines.recv_timeout(Duration::from_secs(2)) {
            self.seen.push(l);
        }
        let out = self.seen.join("\n");
        assert!(status.success(), "{} failed ({status}):\n{out}", self.what);
        out
    }
}

fn subscriber(name: &str, out: &Path, streams: u32) -> Proc {
    let mut p = Proc::spawn(Command::new(c_subscriber()).arg(name).arg(out).arg(streams.to_string()).arg("60"));
    p.wait_for("ready", Duration::from_secs(20));
    p
}

fn producer(name: &str, raw: &Path, steps: u32, extra: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_comgrasp"));
    c.args(["publish", "--name", name, "--text", PROMPT, "--seed", "5"])
        .arg("--bundle")
        .arg(tiny())
        .args(["--min-len", &steps.to_string(), "--max-len", &steps.to_string(), "--raw"])
        .arg(raw)
        .args(extra);
    c
}

fn frames_of(path: &Path) -> Vec<Vec<u8>> {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(bytes.len() % FRAME_BYTES, 0, "{} is not whole frames", path.display());
    bytes.chunks(FRAME_BYTES).map(<[u8]>::to_vec).collect()
}

fn index_of(frame: &[u8]) -> u64 {
    u64::from_le_bytes(frame[8..16].try_into().unwrap())
}

/// The number after `key` in `text` (first occurrence).
fn number(text: &str, key: &str) -> u64 {
    let rest = text.split(key).nth(1).unwrap_or_else(|| panic!("no {key:?} in:\n{text}"));
    rest.split_whitespace().next().unwrap().parse().unwrap()
}

/// The iceoryx2 entries in /dev/shm, but iceoryx2's own machine-wide management segment.
fn shm_segments() -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir("/dev/shm")
        .map(|d| d.filter_map(|e| e.ok()?.file_name().into_string().ok()).collect())
        .unwrap_or_default();
    v.retain(|n| n.starts_with("iox2_") && !n.ends_with("global_mgmt"));
    v.sort();
    v
}

/// Tests here kill processes and count segments, so they run one at a time.
fn serial() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|p| p.into_inner())
}

/// After every process of a test is gone: nothing a killed process held stays behind once
/// dead nodes are reclaimed (what the next publisher or subscriber does by itself).
fn assert_no_stale_segments(before: &[String]) {
    comgrasp::shm::reclaim_dead_nodes().unwrap();
    let after = shm_segments();
    let stale: Vec<&String> = after.iter().filter(|s| !before.contains(s)).collect();
    assert!(stale.is_empty(), "shared-memory segments left behind: {stale:?}");
}

fn name(tag: &str) -> String {
    format!("ipc-{}-{tag}", std::process::id())
}

#[test]
fn a_whole_stream_arrives_in_order_and_bit_identical_in_another_process() {
    let _serial = serial();
    let before = shm_segments();
    let dir = scratch("shm_ipc");
    let n = name("whole");
    let (sub_bin, prod_bin) = (dir.join("whole-sub.bin"), dir.join("whole-prod.bin"));
    let sub = subscriber(&n, &sub_bin, 1);
    let out = run_ok(&mut producer(&n, &prod_bin, 6, &["--wait-subscribers", "1"]), Duration::from_secs(120));
    let sub_out = sub.finish(Duration::from_secs(60));

    let (sent, got) = (frames_of(&prod_bin), frames_of(&sub_bin));
    assert_eq!(sent.len(), 96, "6 token steps of 16 frames\n{out}");
    assert!(sent.iter().enumerate().all(|(i, f)| index_of(f) == i as u64));
    assert!(got == sent, "the subscriber's frames differ from what poll returned");
    assert_eq!(number(&sub_out, "dropped:"), 0, "{sub_out}");
    assert!(sub_out.contains("event started stream 1 frames 0"), "{sub_out}");
    assert!(sub_out.contains(&format!("text \"{PROMPT}\"")), "{sub_out}");
    // ENDED may be read before or after the last frames; the C program reads events first
    // in each round, so it may exit before ENDED arrives: the producer's count is the truth.
    assert_eq!((number(&out, "published:"), number(&out, "skipped:")), (96, 0), "{out}");
    assert_no_stale_segments(&before);
}

#[test]
fn a_killed_subscriber_leaves_the_producer_healthy_and_a_late_one_gets_the_rest() {
    let _serial = serial();
    let before = shm_segments();
    let dir = scratch("shm_ipc");
    let n = name("kill");
    let prod_bin = dir.join("kill-prod.bin");
    let late_bin = dir.join("kill-late.bin");
    let mut doomed = subscriber(&n, &dir.join("kill-doomed.bin"), 1);
    // 18 steps (the tiny model's L_max) = 288 frames, polled every 5 ms through a 4-frame
    // ring: ~1.5 s of streaming.
    let mut prod = Proc::spawn(&mut producer(&n, &prod_bin, 18, PACED));
    prod.wait_for("ready", Duration::from_secs(60));
    std::thread::sleep(Duration::from_millis(300));
    doomed.child.kill().unwrap(); // SIGKILL: no cleanup of its shared memory
    doomed.child.wait().unwrap();
    let late = subscriber(&n, &late_bin, 1);
    let t0 = Instant::now();
    let out = prod.finish(Duration::from_secs(60));
    let late_out = late.finish(Duration::from_secs(60));
    assert!(t0.elapsed() < Duration::from_secs(30), "the producer stalled");

    let sent = frames_of(&prod_bin);
    assert_eq!(sent.len(), 288);
    assert_eq!((number(&out, "published:"), number(&out, "skipped:")), (288, 0), "{out}");
    let got = frames_of(&late_bin);
    let first = index_of(&got[0]) as usize;
    assert!(first > 0 && first < 287, "the late subscriber should join mid-stream, got frames from {first}");
    assert!(got[..] == sent[first..], "the late subscriber must get every frame from its first on, bit-identical");
    assert_eq!(number(&late_out, "dropped:"), 0, "{late_out}");
    assert_no_stale_segments(&before);
}

#[test]
fn a_subscriber_stays_through_a_publisher_killed_and_restarted() {
    let _serial = serial();
    let before = shm_segments();
    let dir = scratch("shm_ipc");
    let n = name("restart");
    let sub_bin = dir.join("restart-sub.bin");
    let sub = subscriber(&n, &sub_bin, 1);
    // The first publisher dies mid-stream (SIGKILL), without cleaning up anything.
    let mut first = Proc::spawn(&mut producer(&n, &dir.join("restart-1.bin"), 18, PACED));
    first.wait_for("ready", Duration::from_secs(60));
    std::thread::sleep(Duration::from_millis(300));
    first.child.kill().unwrap();
    first.child.wait().unwrap();
    // A new publisher under the same name: its stream reaches the same subscriber.
    let second_bin = dir.join("restart-2.bin");
    let out = run_ok(&mut producer(&n, &second_bin, 6, &["--wait-subscribers", "1"]), Duration::from_secs(120));
    sub.finish(Duration::from_secs(60));
    let got = frames_of(&sub_bin);
    let sent = frames_of(&second_bin);
    assert!(got.len() > sent.len(), "frames of the first publisher came before");
    assert!(got[got.len() - sent.len()..] == sent[..], "the restarted publisher's stream arrives whole and identical");
    assert_eq!(number(&out, "skipped:"), 0, "{out}");
    assert_no_stale_segments(&before);
}
