//! Command scripts: timed commands that drive a rollout.
//!
//! A script is a list of segments, each starting at a time in seconds and
//! holding until the next one. The JSON form (`--script FILE.json`):
//!
//! ```json
//! {
//!   "name": "square-ish",
//!   "commands": [
//!     { "at": 0.0, "gait": "stand" },
//!     { "at": 0.5, "velocity": [0.0, 2.5], "gait": "walk" },
//!     { "at": 3.0, "velocity": [0.0, 2.5], "gait": "walk", "turn": 0.6 },
//!     { "at": 6.0, "velocity": [2.0, 0.0], "facing": [0.0, 1.0],
//!       "gait": { "jog": 1.0 } }
//!   ]
//! }
//! ```
//!
//! | field | default | meaning |
//! |---|---|---|
//! | `at` | required | start, seconds (frame `round(at * 60)`); segments in increasing order |
//! | `velocity` | `[0, 0]` | world `(x, z)`, capture units per frame (2.5 walks, 4.5 jogs) |
//! | `facing` | none | world `(x, z)` to face while moving (strafe); none faces where it goes |
//! | `gait` | `"walk"` | `"stand"`, `"walk"`, `"jog"`, `"crouch"`, or weights `{"stand", "walk", "jog", "crouch"}` (missing = 0) |
//! | `turn` | `0` | radians per second by which velocity and facing rotate during the segment (positive turns left, toward `+x` from `+z`) |
//!
//! Values are passed to the controller as they are: out-of-range ones are
//! clamped by the controller, NaN cannot be written in JSON.

use anyhow::{bail, Context, Result};
use phasegate_controller::geom::turn2;
use phasegate_controller::{Command, Gait, GaitWeights};
use serde::Deserialize;
use std::path::Path;

/// Frames per second of PFNN's capture and of every rollout.
pub const FRAME_RATE: f64 = 60.0;

/// Names of the built-in scripts.
pub const BUILTIN: [&str; 6] = [
    "idle",
    "walk",
    "circle-left",
    "zigzag",
    "jog-stop-jog",
    "crouch-walk",
];

/// Largest `turn` of a segment, radians per second: ten turns a second;
/// beyond it the heading is noise.
pub const MAX_TURN: f64 = 20.0 * std::f64::consts::PI;

/// One timed command.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
    /// Start, seconds.
    pub at: f64,
    /// World velocity `(x, z)`, units per frame.
    pub velocity: [f32; 2],
    /// World facing `(x, z)`, if any.
    pub facing: Option<[f32; 2]>,
    /// Gait weights.
    pub gait: GaitWeights,
    /// Rotation of velocity and facing, radians per second.
    pub turn: f64,
}

/// A segment as written in JSON. The gait is read as a raw value and
/// converted by hand: serde's untagged enums cannot read numbers when
/// `serde_json`'s `arbitrary_precision` feature is on, which another crate
/// in the workspace turns on.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSegment {
    at: f64,
    #[serde(default)]
    velocity: [f32; 2],
    #[serde(default)]
    facing: Option<[f32; 2]>,
    #[serde(default)]
    gait: Option<serde_json::Value>,
    #[serde(default)]
    turn: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScript {
    #[serde(default)]
    name: String,
    commands: Vec<RawSegment>,
}

/// A gait by name (`"walk"`) or by weights (`{"walk": 0.5, "jog": 0.5}`).
fn parse_gait(v: Option<&serde_json::Value>) -> Result<GaitWeights> {
    use serde_json::Value;
    let Some(v) = v else {
        return Ok(Gait::Walk.into());
    };
    match v {
        Value::String(s) => Ok(match s.as_str() {
            "stand" => Gait::Stand,
            "walk" => Gait::Walk,
            "jog" => Gait::Jog,
            "crouch" => Gait::Crouch,
            _ => bail!("unknown gait {s:?}: expected stand, walk, jog or crouch"),
        }
        .into()),
        Value::Object(m) => {
            let mut w = GaitWeights::default();
            for (k, x) in m {
                let x = x
                    .as_f64()
                    .ok_or_else(|| anyhow::anyhow!("gait weight {k:?} is not a number"))?
                    as f32;
                match k.as_str() {
                    "stand" => w.stand = x,
                    "walk" => w.walk = x,
                    "jog" => w.jog = x,
                    "crouch" => w.crouch = x,
                    _ => bail!("unknown gait weight {k:?}"),
                }
            }
            Ok(w)
        }
        _ => bail!("gait must be a name or an object of weights"),
    }
}

/// A command script.
#[derive(Clone, Debug, PartialEq)]
pub struct Script {
    /// Name, for reports.
    pub name: String,
    /// Segments, in time order.
    pub commands: Vec<Segment>,
}

fn seg(at: f64, velocity: [f32; 2], gait: Gait) -> Segment {
    Segment {
        at,
        velocity,
        facing: None,
        gait: gait.into(),
        turn: 0.0,
    }
}

impl Script {
    /// A built-in script by name (see [`BUILTIN`]). All start with half a
    /// second of standing, so the character settles from the mean pose.
    pub fn builtin(name: &str) -> Option<Script> {
        use Gait::*;
        let still = seg(0.0, [0.0; 2], Stand);
        let diag = 2.5 * std::f32::consts::FRAC_1_SQRT_2;
        let commands = match name {
            "idle" => vec![still],
            "walk" => vec![still, seg(0.5, [0.0, 2.5], Walk)],
            // 0.6 rad/s at 150 units/s: a circle of radius 250 units.
            "circle-left" => vec![
                still,
                Segment {
                    turn: 0.6,
                    ..seg(0.5, [0.0, 2.5], Walk)
                },
            ],
            "zigzag" => {
                let mut c = vec![still];
                for (i, at) in [0.5, 2.0, 3.5, 5.0, 6.5, 8.0, 9.5].into_iter().enumerate() {
                    let side = if i % 2 == 0 { diag } else { -diag };
                    c.push(seg(at, [side, diag], Walk));
                }
                c
            }
            "jog-stop-jog" => vec![
                still,
                seg(0.5, [0.0, 4.5], Jog),
                seg(3.5, [0.0; 2], Stand),
                seg(6.0, [0.0, 4.5], Jog),
            ],
            "crouch-walk" => vec![still, seg(0.5, [0.0, 2.0], Crouch)],
            _ => return None,
        };
        Some(Script {
            name: name.to_string(),
            commands,
        })
    }

    /// A JSON script (see the module documentation).
    pub fn from_json(text: &str) -> Result<Script> {
        let raw: RawScript = serde_json::from_str(text).context("script JSON")?;
        if raw.commands.is_empty() {
            bail!("script has no commands");
        }
        let mut commands = Vec::new();
        for (i, c) in raw.commands.into_iter().enumerate() {
            if !c.at.is_finite() || c.at < 0.0 || !c.turn.is_finite() {
                bail!("command {i}: `at` must be a finite non-negative time and `turn` finite");
            }
            if c.turn.abs() > MAX_TURN {
                bail!(
                    "command {i}: turn = {:e} rad/s, at most {MAX_TURN:.1} (ten turns a second)",
                    c.turn
                );
            }
            let gait = parse_gait(c.gait.as_ref()).with_context(|| format!("command {i}"))?;
            // JSON has no infinities: a non-finite f32 here was a finite
            // number beyond f32's range, which the controller would refuse
            // at its frame without naming the script.
            let fields = [
                ("velocity[0]", Some(c.velocity[0])),
                ("velocity[1]", Some(c.velocity[1])),
                ("facing[0]", c.facing.map(|f| f[0])),
                ("facing[1]", c.facing.map(|f| f[1])),
                ("gait.stand", Some(gait.stand)),
                ("gait.walk", Some(gait.walk)),
                ("gait.jog", Some(gait.jog)),
                ("gait.crouch", Some(gait.crouch)),
            ];
            if let Some((field, _)) = fields
                .iter()
                .find(|(_, v)| v.is_some_and(|v| !v.is_finite()))
            {
                bail!("command {i}: {field} is beyond the range of f32 (about 3.4e38)");
            }
            commands.push(Segment {
                at: c.at,
                velocity: c.velocity,
                facing: c.facing,
                gait,
                turn: c.turn,
            });
        }
        let mut s = Script {
            name: raw.name,
            commands,
        };
        if s.commands.windows(2).any(|w| w[1].at < w[0].at) {
            bail!("commands must be in increasing `at` order");
        }
        if s.name.is_empty() {
            s.name = "script".into();
        }
        Ok(s)
    }

    /// A built-in name, a calibration tour's name (`tour-SEED-INDEX`,
    /// [`super::tour::by_name`]), or else a JSON file.
    pub fn load(name_or_path: &str) -> Result<Script> {
        if let Some(s) = Script::builtin(name_or_path) {
            return Ok(s);
        }
        if let Some(s) = super::tour::by_name(name_or_path) {
            return Ok(s);
        }
        let path = Path::new(name_or_path);
        if !path.is_file() {
            bail!(
                "{name_or_path} is neither a built-in script ({}), a tour (tour-SEED-INDEX) nor a file",
                BUILTIN.join(", ")
            );
        }
        let bytes = exporter::atomic::read_input(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let text = String::from_utf8(bytes).map_err(|_| {
            anyhow::anyhow!("{}: not a command script: not UTF-8 text", path.display())
        })?;
        let mut s = Script::from_json(&text).with_context(|| path.display().to_string())?;
        if s.name == "script" {
            s.name = path
                .file_stem()
                .map_or("script".into(), |n| n.to_string_lossy().into_owned());
        }
        Ok(s)
    }

    /// The command at `frame`. The turn is computed with the runtime's own
    /// (libm) trigonometry, so command streams are the same bits on every
    /// host.
    pub fn command(&self, frame: usize) -> Command {
        let t = frame as f64 / FRAME_RATE;
        // Segment boundaries fall on frames: `at` rounds to a frame.
        let starts = |c: &Segment| (c.at * FRAME_RATE).round() as usize <= frame;
        let Some(c) = self.commands.iter().rev().find(|c| starts(c)) else {
            return Command::stand();
        };
        let angle = c.turn * (t - c.at).max(0.0);
        let turn = |v: [f32; 2]| {
            let r = turn2([f64::from(v[0]), f64::from(v[1])], angle);
            [r[0] as f32, r[1] as f32]
        };
        Command {
            velocity: turn(c.velocity),
            facing: c.facing.map_or([0.0; 2], turn),
            gait: c.gait,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtins_exist_and_start_standing() {
        for name in BUILTIN {
            let s = Script::builtin(name).unwrap();
            assert_eq!(s.command(0).gait.stand, 1.0, "{name}");
        }
        assert!(Script::builtin("moonwalk").is_none());
        let walk = Script::builtin("walk").unwrap();
        assert_eq!(walk.command(29).velocity, [0.0, 0.0]);
        assert_eq!(walk.command(30).velocity, [0.0, 2.5]);
    }

    #[test]
    fn circle_turns_left() {
        let c = Script::builtin("circle-left").unwrap();
        let v = c.command(30 + 60).velocity; // one second in: 0.6 rad
        assert!((v[0] - 2.5 * 0.6f32.sin()).abs() < 1e-5 && v[0] > 0.0);
    }

    #[test]
    fn json_scripts_parse_and_are_checked() {
        let s = Script::from_json(
            r#"{"commands": [{"at": 0}, {"at": 1, "velocity": [1, 2], "facing": [1, 0],
                "gait": {"jog": 0.5, "walk": 0.5}, "turn": 0.1}]}"#,
        )
        .unwrap();
        assert_eq!(s.commands.len(), 2);
        let c = s.command(60);
        assert_eq!(c.velocity, [1.0, 2.0]);
        assert_eq!(c.facing, [1.0, 0.0]);
        assert_eq!((c.gait.walk, c.gait.jog), (0.5, 0.5));
        assert_eq!(s.command(0).gait.walk, 1.0);
        assert!(Script::from_json(r#"{"commands": []}"#).is_err());
        assert!(Script::from_json(r#"{"commands": [{"at": 1}, {"at": 0}]}"#).is_err());
        assert!(Script::from_json(r#"{"commands": [{"at": 0, "speed": 3}]}"#).is_err());
        assert!(Script::from_json(r#"{"commands": [{"at": 0, "gait": "run"}]}"#).is_err());
        assert!(Script::load("no-such-script-or-file").is_err());
    }

    /// A finite JSON number that is infinite as f32 is refused when the
    /// script is read, naming the file, the command and the field (not at
    /// its frame, by the controller, naming neither).
    #[test]
    fn numbers_beyond_f32_and_absurd_turns_are_refused_naming_the_field() {
        let dir = tempfile::tempdir().unwrap();
        for (json, says) in [
            (
                r#"{"commands": [{"at": 0}, {"at": 1, "velocity": [0, 1e39]}]}"#,
                "command 1: velocity[1] is beyond the range of f32",
            ),
            (
                r#"{"commands": [{"at": 0, "facing": [-1e300, 0]}]}"#,
                "command 0: facing[0] is beyond the range of f32",
            ),
            (
                r#"{"commands": [{"at": 0, "gait": {"jog": 4e38}}]}"#,
                "command 0: gait.jog is beyond the range of f32",
            ),
            (
                r#"{"commands": [{"at": 0, "turn": 1e39}]}"#,
                "command 0: turn = 1e39 rad/s, at most 62.8 (ten turns a second)",
            ),
        ] {
            let path = dir.path().join("s.json");
            std::fs::write(&path, json).unwrap();
            let e = format!("{:#}", Script::load(path.to_str().unwrap()).unwrap_err());
            assert!(e.starts_with(&format!("{}: {says}", path.display())), "{e}");
        }
    }
}
