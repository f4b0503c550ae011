//! The stream through a constrained, lossy, delayed link (issue 15): `nephele up` runs in a
//! network namespace of its own, joined to this one by a link that this test emulates in
//! userspace: two TUN devices (one here, one moved into the namespace) and, between them,
//! threads that carry every IP packet with a rate (a token bucket with a 200-ms queue, drop
//! tail), a random loss and a delay, the way `tc netem` would (this kernel has no `netem`
//! qdisc). A `loadgen` viewer streams from here through it. Phases, each with 50 ms of delay
//! from the service to the viewer:
//!
//! 1. 5 Mbit/s with 2 % loss (more than this stream needs): the rate holds, frames keep coming;
//! 2. 32 kbit/s, no loss (less than any 640x480 picture of path-traced noise needs): the
//!    composer must cut its bitrate on the receiver's loss reports within a few seconds;
//! 3. 20 Mbit/s for 24 s: it must climb back, and frames keep coming; the full picture
//!    (640x480) returns within the phase (4-14 s in, on the composer's fast climb back).
//!
//! A second test puts headless Chromium behind the same link (the real client page, Chrome's
//! own receiver: its REMB estimate, frequent receiver reports, NACKs, keyframe requests and
//! decoder): the link narrows, Chromium keeps decoding, and the full picture returns once
//! the link widens.
//!
//! Needs root (or CAP_NET_ADMIN), `ip netns` and `/dev/net/tun`; without any of them the tests
//! say which and pass without running. The two run one after the other (each is a whole
//! service and a viewer on a 2-core machine).

use std::net::SocketAddr;
use std::process::Command;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nephele_geometry::SplitMix64;
use nephele_loadgen::{Live, LoadConfig};
use nephele_tests::browser::Browser;
use nephele_tests::client;
use nephele_tests::service::UpService;
use tun_rs::{DeviceBuilder, SyncDevice};

/// One link (and one service behind it) at a time.
static ONE_LINK_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Links made by this process so far: each gets its own names and subnet (a TUN device on
/// this side lives as long as the process).
static LINKS_MADE: AtomicU32 = AtomicU32::new(0);

fn run(args: &[&str]) -> Result<(), String> {
    let out = Command::new(args[0]).args(&args[1..]).output().map_err(|e| format!("{}: {e}", args.join(" ")))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!("{}: {}", args.join(" "), String::from_utf8_lossy(&out.stderr).trim()))
    }
}

/// What the emulated link does to the packets leaving the namespace (the composer's media,
/// the master's HTTP answers); changed between phases.
#[derive(Debug, Clone, Copy)]
struct Shape {
    bits_per_s: f64,
    loss: f64,
    delay: Duration,
}

/// Packets the link carried or dropped, from the namespace towards here.
#[derive(Debug, Default)]
struct LinkCounters {
    delivered: AtomicU64,
    lost: AtomicU64,
    queue_full: AtomicU64,
}

/// The longest queue of the rate limiter before it drops (as `tbf ... latency 200ms`).
const QUEUE: Duration = Duration::from_millis(200);

/// What the link does with one packet.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fate {
    /// It reaches the other end at this instant.
    Arrives(Instant),
    Lost,
    QueueFull,
}

/// A packet of `len` bytes offered to the link at `now`; `busy_until` is when the link
/// finishes sending what it already holds.
fn schedule(shape: &Shape, len: usize, now: Instant, busy_until: &mut Instant, rng: &mut SplitMix64) -> Fate {
    if rng.next_f64() < shape.loss {
        return Fate::Lost;
    }
    let start = (*busy_until).max(now);
    if start.duration_since(now) > QUEUE {
        return Fate::QueueFull;
    }
    let sent = start + Duration::from_secs_f64(len as f64 * 8.0 / shape.bits_per_s);
    *busy_until = sent;
    Fate::Arrives(sent + shape.delay)
}

/// The emulator itself (no privileges needed): serialisation at the rate, the delay on top,
/// drop tail past the queue's 200 ms, and the loss.
#[test]
fn the_emulated_link_delays_queues_and_drops_like_a_wire() {
    let mut rng = SplitMix64::new(7);
    let shape = Shape { bits_per_s: 80_000.0, loss: 0.0, delay: Duration::from_millis(50) };
    let t0 = Instant::now();
    let mut busy = t0;
    // 1000 bytes at 80 kbit/s: 100 ms on the wire, then 50 ms of delay.
    let ms = |m: u64| Duration::from_millis(m);
    assert_eq!(schedule(&shape, 1000, t0, &mut busy, &mut rng), Fate::Arrives(t0 + ms(150)));
    // Offered at once: they queue behind it, 100 ms each.
    assert_eq!(schedule(&shape, 1000, t0, &mut busy, &mut rng), Fate::Arrives(t0 + ms(250)));
    assert_eq!(schedule(&shape, 1000, t0, &mut busy, &mut rng), Fate::Arrives(t0 + ms(350)));
    // The queue now holds 300 ms, past the 200-ms limit: dropped, and the link stays as it was.
    assert_eq!(schedule(&shape, 1000, t0, &mut busy, &mut rng), Fate::QueueFull);
    assert_eq!(busy, t0 + ms(300));
    // Once it drains, a packet goes at once again.
    assert_eq!(schedule(&shape, 1000, t0 + ms(400), &mut busy, &mut rng), Fate::Arrives(t0 + ms(550)));
    // The loss is random at the given rate.
    let lossy = Shape { loss: 0.02, ..shape };
    let mut busy = t0;
    let lost = (0..100_000u64)
        .filter(|&i| {
            let now = t0 + Duration::from_secs(i);
            schedule(&lossy, 100, now, &mut busy, &mut rng) == Fate::Lost
        })
        .count();
    assert!((1_800..2_200).contains(&lost), "{lost} of 100,000 lost at 2 %");
}

/// One direction of the link: a thread that reads packets from `from` and stamps their
/// arrival time, and one that writes them to `to` when due (in order: the delay is constant
/// and the queue first in, first out). `shape: None` carries packets at once, untouched.
fn carry(
    from: Arc<SyncDevice>,
    to: Arc<SyncDevice>,
    shape: Option<Arc<Mutex<Shape>>>,
    counters: Arc<LinkCounters>,
    seed: u64,
) {
    let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
    let drops = counters.clone();
    std::thread::spawn(move || {
        let mut rng = SplitMix64::new(seed);
        let mut busy_until = Instant::now();
        let mut buf = vec![0u8; 65_536];
        // Ends when the device goes away (the namespace deleted) or the writer stops.
        while let Ok(n) = from.recv(&mut buf) {
            let now = Instant::now();
            let fate = match &shape {
                None => Fate::Arrives(now),
                Some(shape) => {
                    let shape = *shape.lock().expect("link shape");
                    schedule(&shape, n, now, &mut busy_until, &mut rng)
                }
            };
            match fate {
                Fate::Arrives(due) => {
                    if tx.send((due, buf[..n].to_vec())).is_err() {
                        break;
                    }
                }
                Fate::Lost => _ = drops.lost.fetch_add(1, Ordering::Relaxed),
                Fate::QueueFull => _ = drops.queue_full.fetch_add(1, Ordering::Relaxed),
            }
        }
    });
    std::thread::spawn(move || {
        for (due, packet) in rx {
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
            if to.send(&packet).is_err() {
                break;
            }
            counters.delivered.fetch_add(1, Ordering::Relaxed);
        }
    });
}

/// A namespace joined to this one by the emulated link; the namespace (and with it its TUN
/// device) is removed when dropped.
struct Link {
    ns: String,
    inside_ip: String,
    shape: Arc<Mutex<Shape>>,
    counters: Arc<LinkCounters>,
}

impl Link {
    fn create(shape: Shape) -> Result<Link, String> {
        let pid = std::process::id();
        let n = LINKS_MADE.fetch_add(1, Ordering::Relaxed);
        let subnet = 20 + (pid * 4 + n) % 200;
        let (ns, inside, outside) = (format!("nlossy{pid}_{n}"), format!("nln{pid}_{n}"), format!("nlh{pid}_{n}"));
        let (inside_ip, outside_ip) = (format!("10.213.{subnet}.2"), format!("10.213.{subnet}.1"));
        let device = |name: &str| {
            DeviceBuilder::new()
                .name(name)
                .packet_information(false)
                .build_sync()
                .map(Arc::new)
                .map_err(|e| format!("a TUN device {name} (/dev/net/tun): {e}"))
        };
        let here = device(&outside)?;
        let there = device(&inside)?;
        run(&["ip", "netns", "add", &ns])?;
        let link = Link { ns, inside_ip, shape: Arc::new(Mutex::new(shape)), counters: Arc::default() };
        // The device keeps working for this process after it moves into the namespace.
        run(&["ip", "link", "set", &inside, "netns", &link.ns])?;
        run(&["ip", "addr", "add", &outside_ip, "peer", &link.inside_ip, "dev", &outside])?;
        run(&["ip", "link", "set", &outside, "up"])?;
        link.exec(&["ip", "addr", "add", &link.inside_ip, "peer", &outside_ip, "dev", &inside])?;
        link.exec(&["ip", "link", "set", &inside, "up"])?;
        link.exec(&["ip", "link", "set", "lo", "up"])?;
        carry(there.clone(), here.clone(), Some(link.shape.clone()), link.counters.clone(), u64::from(pid));
        carry(here, there, None, Arc::new(LinkCounters::default()), 0);
        Ok(link)
    }

    fn exec(&self, args: &[&str]) -> Result<(), String> {
        let mut all = vec!["ip", "netns", "exec", &self.ns];
        all.extend_from_slice(args);
        run(&all)
    }

    /// A page served inside the namespace, read with `curl` there; `None` without `curl`.
    fn fetch(&self, url: &str) -> Option<String> {
        let out = Command::new("ip").args(["netns", "exec", &self.ns, "curl", "-s", url]).output().ok()?;
        out.status.success().then(|| String::from_utf8_lossy(&out.stdout).into_owned())
    }

    /// A counter of a `/metrics` page served inside the namespace; `None` without `curl` or
    /// without the counter.
    fn counter(&self, url: &str, name: &str) -> Option<u64> {
        nephele_tests::metric_value(&self.fetch(url)?, name).map(|v| v as u64)
    }

    fn set(&self, shape: Shape) {
        *self.shape.lock().expect("link shape") = shape;
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        // Deleting the namespace deletes its TUN device; this side's goes with the process.
        let _ = run(&["ip", "netns", "delete", &self.ns]);
    }
}

/// The composer's changes of resolution, as the size each went to.
fn resolutions(log: &str) -> Vec<String> {
    log.lines()
        .filter(|l| l.contains("the stream's resolution follows its bitrate"))
        .filter_map(|l| Some(l.split("to=").nth(1)?.split_whitespace().next()?.to_string()))
        .collect()
}

/// The composer's new encoder bitrates: re-targets, and changes of resolution (which
/// re-create the encoder at the bitrate of the moment).
fn targets(log: &str) -> Vec<u64> {
    let number = |l: &str, key: &str| l.split(key).nth(1)?.split(|c: char| !c.is_ascii_digit()).next()?.parse().ok();
    log.lines()
        .filter_map(|l| {
            if l.contains("the stream's bitrate follows the receiver's feedback") {
                number(l, "to=")
            } else if l.contains("the stream's resolution follows its bitrate") {
                number(l, "bitrate=")
            } else {
                None
            }
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stream_follows_a_shaped_lossy_link_and_keeps_decoding() {
    let _one = ONE_LINK_AT_A_TIME.lock().await;
    let delay = Duration::from_millis(50);
    let mbit = |m: f64| m * 1e6;
    let phases: [(&str, Shape, Duration); 3] = [
        ("5 Mbit/s, 2 % loss", Shape { bits_per_s: mbit(5.0), loss: 0.02, delay }, Duration::from_secs(12)),
        ("32 kbit/s", Shape { bits_per_s: mbit(0.032), loss: 0.0, delay }, Duration::from_secs(15)),
        ("20 Mbit/s", Shape { bits_per_s: mbit(20.0), loss: 0.0, delay }, Duration::from_secs(24)),
    ];
    let link = match Link::create(phases[0].1) {
        Ok(link) => link,
        Err(why) => {
            eprintln!("skipped: this test needs network namespaces and TUN devices (root): {why}");
            return;
        }
    };
    let assets = tempfile::tempdir().expect("an asset folder");
    let http: SocketAddr = format!("{}:8480", link.inside_ip).parse().expect("address");
    let prefix = ["ip", "netns", "exec", link.ns.as_str()];
    let dir = assets.path().to_str().expect("utf-8 path");
    // Objects path traced at 1 sample: noisy pictures, which need more than 32 kbit/s.
    let mut up = UpService::start_in(&prefix, http, 1, &["--bake", "off", "--assets", dir], Duration::from_secs(90));

    let total: Duration = phases.iter().map(|p| p.2).sum();
    let config = LoadConfig {
        url: format!("http://{http}/"),
        width: 640,
        height: 480,
        duration: total + Duration::from_secs(2),
        target_fps: 30.0,
        max_busy_retries: 60,
        ..LoadConfig::default()
    };
    let live = Arc::new(Live::default());
    let viewer = tokio::spawn({
        let live = live.clone();
        async move { nephele_loadgen::run(&config, live).await }
    });
    let connected = Instant::now();
    while live.connected.load(Ordering::Relaxed) == 0 {
        assert!(connected.elapsed() < Duration::from_secs(60), "the viewer did not connect through the link");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let ceiling = 640 * 480 * 30 / 10; // `EncoderSettings::low_latency`: 0.1 bit per pixel at 30 fps
    let mut report = Vec::new();
    let counters = &link.counters;
    let dropped = || (counters.lost.load(Ordering::Relaxed), counters.queue_full.load(Ordering::Relaxed));
    let composer_metrics = format!("http://{}/metrics", up.composer_http.expect("the composer's address"));
    let nacks = || {
        let count = |name| link.counter(&composer_metrics, name);
        Some((count("nephele_composer_nack_resent_total")?, count("nephele_composer_nack_refused_total")?))
    };
    let mut nacks_per_phase = Vec::new();
    let mut link_drops = Vec::new();
    for (name, shape, length) in &phases {
        link.set(*shape);
        let (frames_before, changes_before) = (live.frames.load(Ordering::Relaxed), targets(&up.log_text()).len());
        let resolutions_before = resolutions(&up.log_text()).len();
        let mut full_picture_back = None;
        let (lost_before, full_before) = dropped();
        let nacks_before = nacks();
        let start = Instant::now();
        let mut first_change = None;
        while start.elapsed() < *length {
            tokio::time::sleep(Duration::from_millis(250)).await;
            let log = up.log_text();
            if first_change.is_none() && targets(&log).len() > changes_before {
                first_change = Some(start.elapsed().as_secs_f64());
            }
            if full_picture_back.is_none() && resolutions(&log).iter().skip(resolutions_before).any(|s| s == "640x480")
            {
                full_picture_back = Some(start.elapsed().as_secs_f64());
            }
        }
        let all = targets(&up.log_text());
        let target = all.last().copied().unwrap_or(ceiling);
        let frames = live.frames.load(Ordering::Relaxed) - frames_before;
        let (lost, full) = dropped();
        let phase_nacks = nacks_before.zip(nacks()).map(|(before, after)| (after.0 - before.0, after.1 - before.1));
        nacks_per_phase.push(phase_nacks);
        let (resent, refused) = phase_nacks.map_or(("?".into(), "?".into()), |(a, b)| (a.to_string(), b.to_string()));
        let line = format!(
            "{name}, {} ms delay: {frames} frames in {:.0} s, packets lost {} and dropped by the full queue {}, \
             NACKed packets resent {} and refused {}, {} new encoder bitrates (re-targets and resolution changes), first after {}, target at the end {} kbit/s, \
             back to 640x480 after {}",
            shape.delay.as_millis(),
            length.as_secs_f64(),
            lost - lost_before,
            full - full_before,
            resent,
            refused,
            all.len() - changes_before,
            first_change.map_or("-".into(), |s| format!("{s:.1} s")),
            target / 1000,
            full_picture_back.map_or("-".into(), |s| format!("{s:.1} s"))
        );
        println!("{line}");
        report.push((frames, target, all[changes_before..].to_vec(), full_picture_back));
        link_drops.push(full - full_before);
    }
    let users = tokio::time::timeout(Duration::from_secs(60), viewer)
        .await
        .expect("loadgen ends within a minute of its duration")
        .expect("the viewer task")
        .expect("loadgen runs");
    println!("{}", nephele_loadgen::table(&users));
    let user = &users[0];
    assert!(user.error.is_none(), "{}", nephele_loadgen::table(&users));

    // NACKs are answered where a resend can still help (the 2 % loss), and a narrow link's
    // NACKs do not turn into a storm: the queue of phase 2 drops at most what the stream
    // itself offers (about 8 s of 30 fps at the floor is some 1,500 packets; the unbounded
    // responder had some 30,000 dropped here).
    match nacks_per_phase[0] {
        Some((resent, _)) => assert!(resent > 0, "phase 1: no NACKed packet resent: {nacks_per_phase:?}"),
        None => eprintln!("the composer's NACK counters were not read (no curl in the namespace?): not checked"),
    }
    let full_in_phase_2 = link_drops[1];
    assert!(full_in_phase_2 < 5_000, "phase 2: {full_in_phase_2} packets dropped by the full queue");
    // 1: the link is wider than the stream; 2 % loss neither stops frames nor halves the rate.
    let (frames, target, _, _) = &report[0];
    assert!(*frames >= 3, "phase 1: {frames} frames");
    assert!(*target >= ceiling / 2, "phase 1 (5 Mbit/s, 2 % loss) cut the rate to {target} bit/s");
    // 2: a link narrower than the stream: the rate is cut, on the receiver's loss reports.
    let (_, target, changes, _) = &report[1];
    assert!(!changes.is_empty() && *target <= ceiling / 2, "phase 2 (32 kbit/s): targets {changes:?}");
    // ...and below 0.025 bits per pixel the picture gets smaller (320x240) before the frame
    // rate falls; the viewer's decoder reads the new size from the stream.
    let log = up.log_text();
    let fell = log.lines().find(|l| l.contains("the stream's resolution follows its bitrate"));
    assert!(fell.is_some_and(|l| l.contains("to=320x240")), "no fall of the resolution in the composer's log");
    let smaller = user.frames_by_size.get("320x240").copied().unwrap_or(0);
    assert!(smaller > 0, "no frame of 320x240 reached the viewer: {:?}", user.frames_by_size);
    // 3: a wide link again: the rate climbs back and pictures arrive.
    let (frames, target, changes, back) = &report[2];
    assert!(*frames >= 3, "phase 3: {frames} frames");
    assert!(
        changes.iter().any(|&t| t > report[1].1),
        "phase 3 (20 Mbit/s): no increase: {changes:?}, ended at {target}"
    );
    // ...fast enough for the full picture to return within the phase (at 8 % a second it
    // took some 30 s from the floor).
    assert!(back.is_some(), "phase 3 (20 Mbit/s): still 320x240 after 24 s; targets {changes:?}");
    println!("packets delivered to the viewer's side: {}", counters.delivered.load(Ordering::Relaxed));
    up.interrupt(Duration::from_secs(20));
    drop(link);
}

/// The rate at which a 640x480 picture at 30 fps is coded again after a fall to 320x240
/// (`SCALE_UP_BITS_PER_PIXEL`, 0.05 bits per pixel).
const FULL_PICTURE_BPS: u64 = 460_000;

/// What Chromium's receiver says now: frames decoded, and the size of the last one.
fn decoded(browser: &Browser) -> (u64, u64, u64) {
    let stats = client::inbound_video_stats(browser).unwrap_or_default();
    let n = |k: &str| stats[k].as_u64().unwrap_or(0);
    (n("framesDecoded"), n("frameWidth"), n("frameHeight"))
}

/// Waits up to `limit` until Chromium has decoded `count` frames of `width` pixels across
/// since the call (counted from the first such frame on); the seconds that took, or `None`.
fn frames_of_width(browser: &Browser, width: u64, count: u64, limit: Duration) -> Option<f64> {
    let start = Instant::now();
    let mut first_at_width: Option<u64> = None;
    while start.elapsed() < limit {
        let (frames, w, _) = decoded(browser);
        if w == width {
            let from = *first_at_width.get_or_insert(frames);
            if frames >= from + count {
                return Some(start.elapsed().as_secs_f64());
            }
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    None
}

/// Chromium (the real client page, Chrome's own receiver with its REMB estimate, receiver
/// reports several a second, NACKs and keyframe requests) behind the emulated link, 50 ms
/// away: the link narrows to 150 kbit/s for 15 s and Chromium keeps decoding; once the link
/// is wide again the full picture (640x480) returns at a full rate. The picture stands still
/// (a turning camera makes the one path-tracing worker too slow to fill any link), so how
/// soon the stream falls to 320x240 varies from run to run and is printed, not checked.
#[test]
fn chromium_behind_a_narrowing_link_keeps_decoding_and_gets_the_full_picture_back() {
    let _one = ONE_LINK_AT_A_TIME.blocking_lock();
    let delay = Duration::from_millis(50);
    let wide = Shape { bits_per_s: 5e6, loss: 0.0, delay };
    let link = match Link::create(wide) {
        Ok(link) => link,
        Err(why) => {
            eprintln!("skipped: this test needs network namespaces and TUN devices (root): {why}");
            return;
        }
    };
    let started = Instant::now();
    let at = || format!("[{:5.1} s]", started.elapsed().as_secs_f64());
    let assets = tempfile::tempdir().expect("an asset folder");
    let http: SocketAddr = format!("{}:8480", link.inside_ip).parse().expect("address");
    let prefix = ["ip", "netns", "exec", link.ns.as_str()];
    let dir = assets.path().to_str().expect("utf-8 path");
    let mut up = UpService::start_in(&prefix, http, 1, &["--bake", "off", "--assets", dir], Duration::from_secs(90));
    let sessions = format!("http://{}/v1/sessions", up.composer_http.expect("the composer's address"));
    // The composer's media counters of the session, and a line of them.
    let media = || {
        let all: serde_json::Value = serde_json::from_str(&link.fetch(&sessions)?).ok()?;
        let m = all["sessions"][0]["media"].clone();
        let n = |k: &str| m[k].as_u64().unwrap_or(0);
        let line = format!(
            "{} frames sent, encoder {} kbit/s at level {}, REMB {} kbit/s ({} read, {} ignored), {} resolution changes, {} frames skipped for rate",
            n("frames_sent"),
            n("bitrate_bps") / 1000,
            n("resolution_level"),
            n("receiver_estimate_bps") / 1000,
            n("receiver_estimates"),
            n("receiver_estimates_ignored"),
            n("resolution_changes"),
            n("frames_skipped_for_rate")
        );
        Some((m, line))
    };

    let browser = Browser::start().expect("headless Chromium");
    browser.goto(&format!("http://{http}/?scene=default&width=640&height=480")).expect("open the client");
    client::wait_streaming(&browser, Duration::from_secs(60)).expect("the data channel opens through the link");
    let first = frames_of_width(&browser, 640, 20, Duration::from_secs(30));
    // The composer's answer takes the packets' send time that Chromium offers.
    let answer = browser.execute("return window.nephele.pc.remoteDescription.sdp", Vec::new()).expect("the answer");
    assert!(answer.as_str().is_some_and(|sdp| sdp.contains("abs-send-time")), "no abs-send-time in {answer}");
    println!("{} 5 Mbit/s: 20 frames of 640x480 decoded ({first:?} s); {:?}", at(), media().map(|m| m.1));
    assert!(
        first.is_some(),
        "no 640x480 frames through a 5 Mbit/s link: {:?} {}",
        decoded(&browser),
        client::inbound_video_stats(&browser).unwrap_or_default()
    );

    // The link narrows below what the stream sends: Chromium reports the losses and its REMB,
    // and keeps decoding whatever the stream becomes.
    link.set(Shape { bits_per_s: 150e3, ..wide });
    let (before, _, _) = decoded(&browser);
    let mut widths = std::collections::BTreeSet::new();
    let narrowed = Instant::now();
    while narrowed.elapsed() < Duration::from_secs(15) {
        widths.insert(decoded(&browser).1);
        std::thread::sleep(Duration::from_millis(250));
    }
    let (after, _, _) = decoded(&browser);
    println!(
        "{} 150 kbit/s for 15 s: {} frames decoded, of widths {widths:?}; {:?}",
        at(),
        after - before,
        media().map(|m| m.1)
    );
    assert!(after - before >= 10, "{} frames decoded in 15 s of a 150 kbit/s link", after - before);

    // Wide again: the full picture at a full rate returns. Chromium's REMB said 5-13 kbit/s
    // here for the whole phase (its estimator's minimum after the narrowing), which held the
    // stream at its floor, at 320x240, for good until the controller learnt to ignore such
    // estimates: this is the check that failed.
    link.set(Shape { bits_per_s: 20e6, ..wide });
    let widened = Instant::now();
    let mut back = None;
    while back.is_none() && widened.elapsed() < Duration::from_secs(40) {
        let rate = media().map_or(0, |m| m.0["bitrate_bps"].as_u64().unwrap_or(0));
        if rate >= FULL_PICTURE_BPS && frames_of_width(&browser, 640, 10, Duration::from_secs(1)).is_some() {
            back = Some(widened.elapsed().as_secs_f64());
        }
    }
    println!(
        "{} 20 Mbit/s: 640x480 at {} kbit/s or more after {back:?} s; {:?}",
        at(),
        FULL_PICTURE_BPS / 1000,
        media().map(|m| m.1)
    );
    let log = up.log_text();
    assert!(
        back.is_some(),
        "the full picture did not return within 40 s of a 20 Mbit/s link: {:?}, {:?}, targets {:?}, resolutions {:?}",
        decoded(&browser),
        media().map(|m| m.1),
        targets(&log),
        resolutions(&log)
    );
    assert_eq!(client::state(&browser).expect("the page's state"), "streaming");
    let errors = browser.console_log().expect("console log");
    assert!(client::page_errors(&errors).is_empty(), "JavaScript errors: {errors:?}");
    drop(browser);
    up.interrupt(Duration::from_secs(20));
    drop(link);
}
