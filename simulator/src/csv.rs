//! The two CSV formats anyone can replay their own load with: user sessions (`--trace`) and
//! the farm (`--workers`). Plain comma-separated values, no quoting; `#` starts a comment
//! line; blank lines are skipped; a first line starting with `user` / `worker` is a header.
//! Every error names the file and the line.

use glam::Vec3;

use crate::model::{CameraPath, Detect, SimObject, SimUser, SimWorker, ViewMode};

/// The `--trace` format, as `--help` and the README print it.
pub const TRACE_FORMAT: &str = "\
user,arrive_s,depart_s,fps,width,height,fov_deg,views,objects,radius_m,height_m,speed_deg_s,start_deg[,target]
  user         a label
  arrive_s     when the client asks for a session (seconds from the start)
  depart_s     when it leaves (> arrive_s)
  fps          target frame rate, in (0, 240]
  width,height pixels per view, 1..=8192
  fov_deg      vertical field of view, in (0, 180)
  views        mono | stereo (two eyes, 64 mm) | quilt (45 views, 40 deg cone) |
               quiltN (N views, N in 1..=64)
  objects      ';'-separated name:x:y:z:half_size[:cost_per_ray] (a cube; the same name is the
               same object, and must be described identically wherever it appears)
  camera path  the eye orbits the target: target + (r cos a, r sin a, height_m) with
               a = start_deg + speed_deg_s * (t - arrive_s), looking at the target, +Z up
  target       optional x:y:z (default: the mean of the user's object centres)
example:
  u1,0,10,30,1280,720,50,mono,lego:0:0:0:0.6,2.5,0.5,10,0
  u2,0.5,8,60,960,1080,90,stereo,lego:0:0:0:0.6;tree:2:0:0:1:5,3,1.6,0,90,0:0:0.5";

/// The `--workers` format.
pub const WORKERS_FORMAT: &str = "\
worker,rays_per_s[,jitter,join_s,fail_s,detect,slow_from_s,slow_to_s,slow_factor]
  worker       a label (ids follow line order)
  rays_per_s   throughput for cost-1 rays (e.g. 1.5e8)
  jitter       each batch takes (1 + jitter*u) x its time, u uniform in [-1, 1];
               jitter in [0, 1), default 0.1
  join_s       when it registers (default 0)
  fail_s       when it dies (empty: never)
  detect       drop (its connection closes: noticed at once, the default) | silent (a hang:
               only missed heartbeats and deadlines tell)
  slow_*       a straggler: batches started in [slow_from_s, slow_to_s) take
               slow_factor (>= 1) times longer
example:
  w1,1.5e8
  w2,1.5e8,0.1,0,3.0,drop
  w3,1.5e8,0.1,0,,,2,5,10";

/// A malformed line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{file} line {line}: {message}")]
pub struct CsvError {
    pub file: String,
    pub line: usize,
    pub message: String,
}

/// Non-comment lines with their 1-based numbers, header dropped.
fn records<'a>(text: &'a str, header: &'a str) -> impl Iterator<Item = (usize, Vec<&'a str>)> + 'a {
    let mut first = true;
    text.lines().enumerate().filter_map(move |(i, line)| {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            return None;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let is_header = first && fields[0].eq_ignore_ascii_case(header);
        first = false;
        (!is_header).then_some((i + 1, fields))
    })
}

fn number(text: &str, what: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|_| format!("{what} '{text}' is not a number"))?;
    if !value.is_finite() {
        return Err(format!("{what} '{text}' is not finite"));
    }
    Ok(value)
}

fn positive(text: &str, what: &str) -> Result<f64, String> {
    let value = number(text, what)?;
    if value <= 0.0 {
        return Err(format!("{what} must be positive, got '{text}'"));
    }
    Ok(value)
}

fn optional<'a>(fields: &[&'a str], index: usize) -> Option<&'a str> {
    fields.get(index).copied().filter(|f| !f.is_empty())
}

fn vec3(text: &str, what: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = text.split(':').collect();
    if parts.len() != 3 {
        return Err(format!("{what} '{text}' must be x:y:z"));
    }
    let mut v = [0.0f32; 3];
    for (slot, part) in v.iter_mut().zip(parts) {
        *slot = number(part, what)? as f32;
    }
    Ok(Vec3::from(v))
}

fn parse_object(text: &str) -> Result<SimObject, String> {
    let parts: Vec<&str> = text.split(':').map(str::trim).collect();
    if !(5..=6).contains(&parts.len()) || parts[0].is_empty() {
        return Err(format!("object '{text}' must be name:x:y:z:half_size[:cost_per_ray]"));
    }
    let center = Vec3::new(
        number(parts[1], "object x")? as f32,
        number(parts[2], "object y")? as f32,
        number(parts[3], "object z")? as f32,
    );
    let half_size = positive(parts[4], "object half_size")? as f32;
    let cost_per_ray = match parts.get(5) {
        Some(c) => positive(c, "object cost_per_ray")?,
        None => 1.0,
    };
    Ok(SimObject { name: parts[0].to_string(), center, half_size, cost_per_ray })
}

/// Parses a trace of user sessions; returns the objects (in order of first appearance) and
/// the users, whose `objects` index into them.
pub fn parse_trace(text: &str, file: &str) -> Result<(Vec<SimObject>, Vec<SimUser>), CsvError> {
    let mut objects: Vec<SimObject> = Vec::new();
    let mut users = Vec::new();
    for (line, fields) in records(text, "user") {
        let fail = |message: String| CsvError { file: file.to_string(), line, message };
        if !(13..=14).contains(&fields.len()) {
            return Err(fail(format!(
                "expected 13 or 14 fields (user,arrive_s,depart_s,fps,width,height,fov_deg,views,objects,radius_m,height_m,speed_deg_s,start_deg[,target]), got {}",
                fields.len()
            )));
        }
        let user = (|| -> Result<SimUser, String> {
            let arrive_s = number(fields[1], "arrive_s")?;
            let depart_s = number(fields[2], "depart_s")?;
            if arrive_s < 0.0 || depart_s <= arrive_s {
                return Err(format!("need 0 <= arrive_s < depart_s, got {arrive_s} and {depart_s}"));
            }
            let fps = positive(fields[3], "fps")?;
            if fps > 240.0 {
                return Err(format!("fps {fps} exceeds 240"));
            }
            let size = |text: &str, what: &str| -> Result<u32, String> {
                text.parse::<u32>()
                    .ok()
                    .filter(|v| (1..=8192).contains(v))
                    .ok_or_else(|| format!("{what} '{text}' must be an integer in 1..=8192"))
            };
            let (width, height) = (size(fields[4], "width")?, size(fields[5], "height")?);
            let fov_deg = positive(fields[6], "fov_deg")?;
            if fov_deg >= 180.0 {
                return Err(format!("fov_deg {fov_deg} must be below 180"));
            }
            let views = ViewMode::parse(fields[7])
                .ok_or_else(|| format!("views '{}' must be mono, stereo, quilt or quiltN (N in 1..=64)", fields[7]))?;
            let mut indices = Vec::new();
            for spec in fields[8].split(';').map(str::trim).filter(|s| !s.is_empty()) {
                let object = parse_object(spec)?;
                let index = match objects.iter().position(|o| o.name == object.name) {
                    Some(i) if objects[i] == object => i,
                    Some(_) => return Err(format!("object '{}' is described differently than before", object.name)),
                    None => {
                        objects.push(object);
                        objects.len() - 1
                    }
                };
                if !indices.contains(&index) {
                    indices.push(index);
                }
            }
            if indices.is_empty() {
                return Err("a user needs at least one object".to_string());
            }
            let radius_m = positive(fields[9], "radius_m")? as f32;
            let path = CameraPath {
                target: optional(&fields, 13).map(|t| vec3(t, "target")).transpose()?,
                radius_m,
                height_m: number(fields[10], "height_m")? as f32,
                speed_deg_s: number(fields[11], "speed_deg_s")? as f32,
                start_deg: number(fields[12], "start_deg")? as f32,
            };
            Ok(SimUser {
                name: fields[0].to_string(),
                arrive_s,
                depart_s,
                fps,
                width,
                height,
                fov_deg: fov_deg as f32,
                views,
                objects: indices,
                path,
            })
        })()
        .map_err(fail)?;
        users.push(user);
    }
    if users.is_empty() {
        return Err(CsvError { file: file.to_string(), line: 0, message: "no user sessions in the trace".to_string() });
    }
    Ok((objects, users))
}

/// Parses a farm description.
pub fn parse_workers(text: &str, file: &str) -> Result<Vec<SimWorker>, CsvError> {
    let mut workers = Vec::new();
    for (line, fields) in records(text, "worker") {
        let fail = |message: String| CsvError { file: file.to_string(), line, message };
        if !(2..=9).contains(&fields.len()) {
            return Err(fail(format!(
                "expected 2 to 9 fields (worker,rays_per_s[,jitter,join_s,fail_s,detect,slow_from_s,slow_to_s,slow_factor]), got {}",
                fields.len()
            )));
        }
        let worker = (|| -> Result<SimWorker, String> {
            let mut w = SimWorker::new(fields[0], positive(fields[1], "rays_per_s")?);
            if let Some(j) = optional(&fields, 2) {
                w.jitter = number(j, "jitter")?;
                if !(0.0..1.0).contains(&w.jitter) {
                    return Err(format!("jitter {} must lie in [0, 1)", w.jitter));
                }
            }
            if let Some(j) = optional(&fields, 3) {
                w.join_s = number(j, "join_s")?;
                if w.join_s < 0.0 {
                    return Err(format!("join_s {} must not be negative", w.join_s));
                }
            }
            if let Some(f) = optional(&fields, 4) {
                let fail_s = number(f, "fail_s")?;
                if fail_s <= w.join_s {
                    return Err(format!("fail_s {fail_s} must come after join_s {}", w.join_s));
                }
                w.fail_s = Some(fail_s);
            }
            if let Some(d) = optional(&fields, 5) {
                w.detect = match d {
                    "drop" => Detect::Drop,
                    "silent" => Detect::Silent,
                    other => return Err(format!("detect '{other}' must be drop or silent")),
                };
            }
            let slow: Vec<Option<&str>> = (6..9).map(|i| optional(&fields, i)).collect();
            match slow.as_slice() {
                [None, None, None] => {}
                [Some(from), Some(to), Some(factor)] => {
                    let (from, to, factor) =
                        (number(from, "slow_from_s")?, number(to, "slow_to_s")?, number(factor, "slow_factor")?);
                    if from < 0.0 || to <= from || factor < 1.0 {
                        return Err(format!(
                            "need 0 <= slow_from_s < slow_to_s and slow_factor >= 1, got {from}, {to}, {factor}"
                        ));
                    }
                    w.slow = Some((from, to, factor));
                }
                _ => return Err("slow_from_s, slow_to_s and slow_factor go together".to_string()),
            }
            Ok(w)
        })()
        .map_err(fail)?;
        workers.push(worker);
    }
    if workers.is_empty() {
        return Err(CsvError {
            file: file.to_string(),
            line: 0,
            message: "no workers in the farm description".to_string(),
        });
    }
    Ok(workers)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_documented_examples_parse() {
        let example = |format: &str| {
            format
                .lines()
                .skip_while(|l| !l.starts_with("example"))
                .skip(1)
                .map(str::trim)
                .collect::<Vec<_>>()
                .join("\n")
        };
        let (objects, users) = parse_trace(&example(TRACE_FORMAT), "trace.csv").expect("example trace");
        assert_eq!(users.len(), 2);
        assert_eq!(objects.len(), 2, "lego shared by both users");
        assert_eq!(users[1].objects, vec![0, 1]);
        assert_eq!(users[1].views, ViewMode::Stereo);
        assert_eq!(objects[1].cost_per_ray, 5.0);
        assert_eq!(users[1].path.target, Some(Vec3::new(0.0, 0.0, 0.5)));
        let workers = parse_workers(&example(WORKERS_FORMAT), "farm.csv").expect("example farm");
        assert_eq!(workers.len(), 3);
        assert_eq!((workers[1].fail_s, workers[1].detect), (Some(3.0), Detect::Drop));
        assert_eq!(workers[2].slow, Some((2.0, 5.0, 10.0)));
        let header = "worker,rays_per_s\n# a comment\n\nw1,1e8\n";
        assert_eq!(parse_workers(header, "f").expect("header skipped").len(), 1);
    }

    #[test]
    fn malformed_lines_name_their_line() {
        let good = "u1,0,10,30,64,48,50,mono,a:0:0:0:1,2,0,0,0";
        let cases = [
            ("u1,0,10,30", "expected 13 or 14 fields"),
            ("u1,0,10,-3,64,48,50,mono,a:0:0:0:1,2,0,0,0", "fps must be positive"),
            ("u1,0,10,0,64,48,50,mono,a:0:0:0:1,2,0,0,0", "fps must be positive"),
            ("u1,0,10,nan,64,48,50,mono,a:0:0:0:1,2,0,0,0", "not finite"),
            ("u1,5,1,30,64,48,50,mono,a:0:0:0:1,2,0,0,0", "arrive_s < depart_s"),
            ("u1,0,10,30,0,48,50,mono,a:0:0:0:1,2,0,0,0", "width"),
            ("u1,0,10,30,64,48,50,cube,a:0:0:0:1,2,0,0,0", "views 'cube'"),
            ("u1,0,10,30,64,48,50,mono,a:0:0:1,2,0,0,0", "name:x:y:z:half_size"),
            ("u1,0,10,30,64,48,50,mono,a:0:0:0:2,2,0,0,0", "described differently"),
            ("u1,0,10,30,64,48,50,mono,,2,0,0,0", "at least one object"),
            ("u1,0,10,30,64,48,50,mono,a:0:0:0:1,2,0,0,0,1:2", "x:y:z"),
            ("u1,0,10,30,64,48,50,mono,a:0:0:0:1,abc,0,0,0", "radius_m 'abc' is not a number"),
        ];
        for (bad, expected) in cases {
            let text = format!("# header comment\n{good}\n\n{bad}\n");
            let err = parse_trace(&text, "t.csv").expect_err(bad);
            assert_eq!(err.line, 4, "{bad}: {err}");
            assert!(err.to_string().starts_with("t.csv line 4: "), "{err}");
            assert!(err.message.contains(expected), "{bad}: {err}");
        }
        let worker_cases = [
            ("w", "expected 2 to 9 fields"),
            ("w,0", "must be positive"),
            ("w,1e8,1.5", "jitter"),
            ("w,1e8,0.1,2,1", "fail_s"),
            ("w,1e8,0.1,0,3,explode", "detect"),
            ("w,1e8,0.1,0,,,2,1,3", "slow_from_s < slow_to_s"),
            ("w,1e8,0.1,0,,,2,5", "go together"),
        ];
        for (bad, expected) in worker_cases {
            let err = parse_workers(&format!("w0,1e8\n{bad}"), "farm.csv").expect_err(bad);
            assert_eq!(err.line, 2, "{bad}");
            assert!(err.message.contains(expected), "{bad}: {err}");
        }
        assert!(parse_workers("# nothing\n", "farm.csv").is_err());
        assert!(parse_trace("", "t.csv").is_err());
    }
}
