//! The chain ending in a real control: LinuxCNC (uspace, no GUI) runs a simulated mill
//! whose axes X and Z carry the compgate NC axis modules of `deploy/linuxcnc`. The gateway
//! writes SD43900/43910/43920 into it over Modbus TCP, and LinuxCNC's own motion
//! controller moves the axis by SD43900 + SD43910 * (X - SD43920). Without LinuxCNC the
//! tests skip (fail under `CI`). LinuxCNC runs once per machine (its HAL lives in
//! fixed shared memory): the tests take turns.
#![allow(clippy::unwrap_used)]

mod common;

use std::io::Write;
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use common::{start_edited, with_target, written_by_model};
use compgate_core::comp::CompParams;
use compgate_gateway::nc::modbus::{ModbusNcWriter, ModbusTargetConfig};
use compgate_gateway::nc::{Job, NcError, NcSnapshot, NcWriter};
use compgate_ncproto::{var, JobStatus};
use tokio_modbus::client::{Reader, Writer};
use tokio_modbus::ExceptionCode;

/// One count of the external offset (the eoffset-scale `compgate_nc.tcl` sets), mm.
const COUNT_MM: f64 = 1e-6;

/// Held by the test whose LinuxCNC runs.
static ONE_LINUXCNC: Mutex<()> = Mutex::new(());

/// A running LinuxCNC; dropping it shuts it down.
struct LinuxCnc {
    child: Child,
    ctl: Option<ChildStdin>,
    dir: tempfile::TempDir,
    _turn: MutexGuard<'static, ()>,
}

impl LinuxCnc {
    /// Starts `tests/linuxcnc/machine.ini` and waits until the machine is on, homed and
    /// the modules serve; `None` when LinuxCNC is not installed (see [`Self::launch`]).
    fn start() -> Option<Self> {
        let mut cnc = Self::launch(None)?;
        cnc.wait_ready();
        Some(cnc)
    }

    fn wait_ready(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(60);
        // motion.is-all-homed reads TRUE for a moment at start, before any joint is.
        while !([
            "motion.motion-enabled",
            "motion.is-all-homed",
            "joint.0.homed",
        ]
        .iter()
        .all(|p| self.pin(p) == "TRUE")
            && ["x", "z"].iter().all(|a| {
                !matches!(
                    self.pin(&format!("compgate-nc-{a}.port")).as_str(),
                    "" | "0"
                )
            }))
        {
            if let Some(status) = self.child.try_wait().unwrap() {
                panic!(
                    "LinuxCNC ended ({status}) before it was ready\n{}",
                    self.logs()
                );
            }
            assert!(
                Instant::now() < deadline,
                "LinuxCNC not on, homed and serving within 60 s\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Shuts LinuxCNC down and starts it again in the same directory.
    fn restart(mut self) -> Self {
        self.stop();
        self.child = Self::spawn(self.dir.path());
        self.ctl = self.child.stdin.take();
        self.wait_ready();
        self
    }

    /// Starts `tests/linuxcnc/machine.ini` in a temporary directory, with `edit`
    /// (file, text, replacement) made to its files; `None` (after saying why) when
    /// LinuxCNC is not installed and `CI` is unset.
    fn launch(edit: Option<(&str, &str, &str)>) -> Option<Self> {
        let installed = Command::new("sh")
            .args(["-c", "command -v linuxcnc halcmd"])
            .stdout(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !installed {
            let why = "LinuxCNC is missing (Debian package linuxcnc-uspace; test.sh installs it)";
            assert!(std::env::var_os("CI").is_none(), "{why} (CI is set)");
            eprintln!("skipped: {why}");
            return None;
        }
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        for (from, name) in [
            ("tests/linuxcnc", "machine.ini"),
            ("tests/linuxcnc", "machine.hal"),
            ("tests/linuxcnc", "machine_ctl.py"),
            ("deploy/linuxcnc", "compgate_nc.tcl"),
            ("deploy/linuxcnc", "compgate_nc.py"),
        ] {
            std::fs::copy(root.join(from).join(name), dir.path().join(name)).unwrap();
        }
        std::fs::write(dir.path().join("tool.tbl"), "").unwrap();
        if let Some((file, from, to)) = edit {
            // An empty `from` makes the file, with `to` in it.
            let path = dir.path().join(file);
            let text = std::fs::read_to_string(&path).unwrap_or_default();
            assert!(text.contains(from), "{file} has no {from:?}");
            let text = if from.is_empty() {
                to.to_string()
            } else {
                text.replace(from, to)
            };
            std::fs::write(&path, text).unwrap();
        }
        let turn = ONE_LINUXCNC.lock().unwrap_or_else(|e| e.into_inner());
        let comps = Command::new("halcmd")
            .args(["list", "comp"])
            .output()
            .unwrap();
        let comps = String::from_utf8_lossy(&comps.stdout).to_string();
        assert!(
            comps.split_whitespace().all(|c| c.starts_with("halcmd")),
            "a LinuxCNC (or another HAL) runs on this machine already, with {comps}: \
             the test needs LinuxCNC to itself"
        );
        if running_as_root() {
            // rtapi_app refuses root without a user to fall back to, who must be able
            // to make its FIFO (and the module its setting data file).
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o777)).unwrap();
        }
        let mut child = Self::spawn(dir.path());
        let ctl = child.stdin.take();
        Some(Self {
            child,
            ctl,
            dir,
            _turn: turn,
        })
    }

    /// `linuxcnc machine.ini` in `dir`.
    fn spawn(dir: &Path) -> Child {
        let mut cmd = Command::new("linuxcnc");
        cmd.arg("machine.ini")
            .current_dir(dir)
            // Its logs (linuxcnc_print.txt, linuxcnc_debug.txt) land in the directory.
            .env("HOME", dir)
            .env_remove("DISPLAY")
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        if running_as_root() {
            cmd.env("RTAPI_UID", "65534")
                .env("RTAPI_FIFO_PATH", dir.join("rtapi_fifo"));
        }
        cmd.spawn().unwrap()
    }

    /// Waits up to 60 s for LinuxCNC to end by itself (a start that fails) and returns
    /// its logs.
    fn exit_logs(mut self) -> String {
        let deadline = Instant::now() + Duration::from_secs(60);
        while self.child.try_wait().unwrap().is_none() {
            assert!(Instant::now() < deadline, "LinuxCNC still runs after 60 s");
            std::thread::sleep(Duration::from_millis(100));
        }
        self.logs()
    }

    /// A HAL pin's value as halcmd prints it; empty while it does not exist.
    fn pin(&self, name: &str) -> String {
        let out = Command::new("halcmd")
            .args(["getp", name])
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).trim().to_string()
    }

    fn set_pin(&self, name: &str, value: &str) {
        let out = Command::new("halcmd")
            .args(["setp", name, value])
            .output()
            .unwrap();
        assert!(out.status.success(), "setp {name} {value}: {out:?}");
    }

    /// A float pin at full precision (halcmd prints 7 digits).
    fn pin_f64(&self, name: &str) -> f64 {
        let out = Command::new("/usr/bin/python3")
            .args([
                "-c",
                "import hal, os, sys\n\
                 c = hal.component(f'compgate-test-{os.getpid()}')\n\
                 print(repr(hal.get_value(sys.argv[1])))\n\
                 c.exit()",
                name,
            ])
            .output()
            .unwrap();
        let v = String::from_utf8_lossy(&out.stdout).trim().to_string();
        v.parse().unwrap_or_else(|_| {
            panic!(
                "pin {name}: {v:?} {}\n{}",
                String::from_utf8_lossy(&out.stderr),
                self.logs()
            )
        })
    }

    /// Waits up to `secs` for `pred`; panics naming `what`, with LinuxCNC's logs.
    fn wait(&self, secs: f64, what: &str, pred: impl Fn(&Self) -> bool) {
        let deadline = Instant::now() + Duration::from_secs_f64(secs);
        while !pred(self) {
            assert!(
                Instant::now() < deadline,
                "no {what} within {secs} s\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// A command of `machine_ctl.py`: `mdi G-CODE`, `off`, `on`.
    fn command(&mut self, line: &str) {
        writeln!(self.ctl.as_mut().unwrap(), "{line}").unwrap();
    }

    /// Where the module of `axis` (`x`, `z`) serves.
    fn address(&self, axis: &str) -> String {
        format!(
            "127.0.0.1:{}",
            self.pin(&format!("compgate-nc-{axis}.port"))
        )
    }

    /// The keys of a `[targets.NAME] kind = "modbus"` table for the module of `axis`.
    fn target_keys(&self, axis: &str) -> String {
        format!(
            "address = \"{}\"\nunit_id = 1\ntimeout_s = 0.5\njob_timeout_s = 0.5\n",
            self.address(axis)
        )
    }

    fn writer(&self, axis: &str) -> ModbusNcWriter {
        toml::from_str::<ModbusTargetConfig>(&self.target_keys(axis))
            .unwrap()
            .writer()
    }

    /// What LinuxCNC's start script and its components logged: in `/tmp` while it
    /// runs, in its `HOME` once it ended.
    fn logs(&self) -> String {
        let mut text: String = ["linuxcnc_print.txt", "linuxcnc_debug.txt"]
            .iter()
            .map(|f| std::fs::read_to_string(self.dir.path().join(f)).unwrap_or_default())
            .collect();
        for entry in std::fs::read_dir("/tmp").into_iter().flatten().flatten() {
            let name = entry.file_name().to_string_lossy().to_string();
            if name.starts_with("linuxcnc.print.") || name.starts_with("linuxcnc.debug.") {
                let log = std::fs::read_to_string(entry.path()).unwrap_or_default();
                if log.contains(&self.dir.path().display().to_string()) {
                    text += &format!("--- {name}\n{log}");
                }
            }
        }
        text
    }
}

impl LinuxCnc {
    /// Shuts LinuxCNC down: its input closed, the display program ends and LinuxCNC
    /// stops; after 30 s it is killed.
    fn stop(&mut self) {
        drop(self.ctl.take());
        let deadline = Instant::now() + Duration::from_secs(30);
        while Instant::now() < deadline {
            if self.child.try_wait().ok().flatten().is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = Command::new("halrun").arg("-U").status();
    }
}

impl Drop for LinuxCnc {
    fn drop(&mut self) {
        self.stop();
    }
}

fn running_as_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("Uid:"))
        .and_then(|ids| ids.split_whitespace().next())
        == Some("0")
}

/// The offset the 840D formula gives at `at_mm` for what a module holds.
fn offset_mm(held: &NcSnapshot, at_mm: f64) -> f64 {
    held.sd43900_mm + held.sd43910 * (at_mm - held.sd43920_mm)
}

/// Waits until LinuxCNC's `axis` (joint `joint`) stands at `at_mm` and applies what its
/// module holds (`w`'s snapshot, MD32750 bits applied by `formula`): the external
/// offset within one count, and the joint commanded at the position plus it.
async fn wait_applied(
    cnc: &LinuxCnc,
    w: &mut ModbusNcWriter,
    (axis, joint): (&str, u8),
    at_mm: f64,
    formula: fn(&NcSnapshot, f64) -> f64,
) -> (NcSnapshot, f64) {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let at = cnc.pin_f64(&format!("axis.{axis}.pos-cmd"));
        let eoffset = cnc.pin_f64(&format!("axis.{axis}.eoffset"));
        let joint_mm = cnc.pin_f64(&format!("joint.{joint}.pos-cmd"));
        // After the pins: once the axis stands, the module's position is the pins'.
        let held = w.read_snapshot().await.unwrap();
        if at == at_mm
            && (eoffset - formula(&held, at)).abs() <= COUNT_MM
            && (joint_mm - (at + eoffset)).abs() < 1e-9
        {
            return (held, eoffset);
        }
        assert!(
            Instant::now() < deadline,
            "at {axis} = {at} (waiting for {at_mm}) LinuxCNC applies {eoffset} mm (joint at \
             {joint_mm}); the formula gives {} for {held:?}",
            formula(&held, at)
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_chain_moves_a_linuxcnc_axis_by_the_840d_formula() {
    let Some(mut cnc) = LinuxCnc::start() else {
        return;
    };
    let mut w = cnc.writer("x");
    let x = ("x", 0);

    // What the module reports from the INI file and HAL before any job.
    let held = w.read_snapshot().await.unwrap();
    assert_eq!(
        (held.md32750, held.referenced),
        (Some(3), Some(true)),
        "{held:?}"
    );
    assert_eq!(held.max_ax_velo_mm_per_min, 200.0 * 60.0);
    assert_eq!(held.md32760, 0.2, "OFFSET_AV_RATIO");
    assert_eq!(held.md32450_mm, 0.003, "[JOINT_0]BACKLASH");

    // Outside the map the module answers with the exceptions the map documents.
    let mut raw = tokio_modbus::client::tcp::connect(cnc.address("x").parse().unwrap())
        .await
        .unwrap();
    for (request, expected) in [
        // 136..139 are not in the map; the servo block is not served.
        (
            raw.read_holding_registers(100, 42).await,
            ExceptionCode::IllegalDataAddress,
        ),
        (
            raw.read_holding_registers(1100, 10).await,
            ExceptionCode::IllegalDataAddress,
        ),
        (
            raw.read_holding_registers(0, 126).await,
            ExceptionCode::IllegalDataValue,
        ),
        (
            raw.read_input_registers(0, 1).await,
            ExceptionCode::IllegalFunction,
        ),
    ] {
        assert_eq!(request.unwrap(), Err(expected));
    }
    // The read-back block is read-only.
    assert_eq!(
        raw.write_single_register(100, 1).await.unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );

    // The module refuses what an 840D refuses, all or none.
    common::refused_all_or_none(&mut w).await;
    let machine_data = Job {
        pairs: vec![(var::MD32750, 0.0)],
    };
    let e = w.write_job(&machine_data).await.unwrap_err();
    assert!(
        matches!(
            e,
            NcError::Refused {
                status: JobStatus::AccessDenied,
                ..
            }
        ),
        "{e:?}"
    );
    assert_eq!(w.read_snapshot().await.unwrap().sd43910, 0.0);

    // The gateway: transmitters -> filter -> model -> a verified job on LinuxCNC.
    // The plant simulates every Modbus target: this one is pointed at LinuxCNC.
    let target = format!(
        "[targets.nc_x]\nkind = \"modbus\"\n{}",
        cnc.target_keys("x")
    );
    let address = cnc.address("x");
    let mut rig = start_edited(&with_target(&target, 1), |c| {
        c.modbus_target_mut("nc_x").unwrap().address = address;
    })
    .await;
    let s = rig
        .wait_for(20.0, "a verified job on LinuxCNC", |s| {
            s.axes[0].jobs_ok >= 1
        })
        .await;
    let written = written_by_model(&s);
    let held = w.read_snapshot().await.unwrap();
    assert_eq!(held.sd43900_mm.to_bits(), written.k0_mm.to_bits());
    assert_eq!(held.sd43910.to_bits(), written.tan_beta.to_bits());
    assert_eq!(held.sd43920_mm, 100.0);

    // At home (X = 0) and at X = 300 the axis moves by the formula at its position:
    // the slope term is applied in the servo thread, not once per job.
    let (_, at_home) = wait_applied(&cnc, &mut w, x, 0.0, offset_mm).await;
    cnc.command("mdi G0 X300");
    let (held, at_300) = wait_applied(&cnc, &mut w, x, 300.0, offset_mm).await;
    assert!(
        (at_300 - at_home - held.sd43910 * 300.0).abs() <= 2.0 * COUNT_MM,
        "{at_home} at X 0, {at_300} at X 300, SD43910 {}",
        held.sd43910
    );
    assert!(at_300 > 0.04, "{at_300}");
    // The module reports LinuxCNC's position and offset back.
    assert_eq!(held.position_mm, Some(300.0));
    assert_eq!(
        held.applied_comp_mm.map(f64::to_bits),
        Some(at_300.to_bits())
    );

    // Z's module (MD32750 = 1) is its own: SD43900 alone moves Z, X keeps its offset.
    let mut wz = cnc.writer("z");
    assert_eq!(wz.read_snapshot().await.unwrap().md32750, Some(1));
    let z_job = CompParams {
        k0_mm: -0.0125,
        tan_beta: 0.001,
        p0_mm: 0.0,
    };
    wz.write_job(&Job::thermal(&z_job)).await.unwrap();
    cnc.command("mdi G0 Z50");
    let (_, z_offset) = wait_applied(&cnc, &mut wz, ("z", 2), 50.0, |h, _| h.sd43900_mm).await;
    assert!((z_offset + 0.0125).abs() <= COUNT_MM, "{z_offset}");
    // LinuxCNC drops the offset changes it gets while the offset is switched off (as it
    // does before every joint is homed): switched on again, Z still gets the new value.
    cnc.set_pin("axis.z.eoffset-enable", "0");
    let z_job = CompParams {
        k0_mm: 0.02,
        ..z_job
    };
    wz.write_job(&Job::thermal(&z_job)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    cnc.set_pin("axis.z.eoffset-enable", "1");
    wait_applied(&cnc, &mut wz, ("z", 2), 50.0, |h, _| h.sd43900_mm).await;
    wait_applied(&cnc, &mut w, x, 300.0, offset_mm).await;

    // Machine off: no offset is requested (LinuxCNC restarts its offset register from
    // zero at the next machine on); on again, the offset is applied again.
    cnc.command("off");
    cnc.wait(10.0, "zero offset counts with the machine off", |c| {
        c.pin("motion.motion-enabled") == "FALSE" && c.pin("axis.x.eoffset-counts") == "0"
    });
    cnc.command("on");
    // Switched on, LinuxCNC takes the joint's position, offset included, as the new X.
    cnc.wait(10.0, "the machine on again", |c| {
        c.pin("motion.motion-enabled") == "TRUE"
    });
    let at = cnc.pin_f64("axis.x.pos-cmd");
    wait_applied(&cnc, &mut w, x, at, offset_mm).await;
    let before = rig.stop_without_failed_jobs().await;

    // The module retains the setting data, as the 840D does: after a restart of
    // LinuxCNC it holds, bit for bit, what the gateway wrote last, and applies it.
    let last = before.axes[0].written.unwrap();
    let cnc = cnc.restart();
    let mut w = cnc.writer("x");
    let (held, _) = wait_applied(&cnc, &mut w, x, 0.0, offset_mm).await;
    assert_eq!(held.thermal(), last);
    assert_ne!(held.sd43900_mm, 0.0);
    // And Z's.
    let mut wz = cnc.writer("z");
    let (held_z, _) = wait_applied(&cnc, &mut wz, ("z", 2), 0.0, |h, _| h.sd43900_mm).await;
    assert_eq!(held_z.thermal(), z_job);
}

#[test]
fn a_setup_the_module_cannot_serve_stops_linuxcnc_naming_the_key() {
    // A port another program listens on.
    let taken = std::net::TcpListener::bind("0.0.0.0:0").unwrap();
    let taken_port = taken.local_addr().unwrap().port();
    let z_port = format!("[COMPGATE_Z]\nJOINT = 2\nPORT = {taken_port}\n");
    let z_port_error = format!("cannot listen on 0.0.0.0:{taken_port}: Address already in use");
    for (edit, expected) in [
        (
            (
                "machine.ini",
                "[COMPGATE_Z]\nJOINT = 2\nPORT = 0\n",
                "[COMPGATE_Z]\nJOINT = 2\n",
            ),
            "[COMPGATE_Z]PORT is missing from the INI file",
        ),
        (
            ("machine.ini", "LINEAR_UNITS = mm", "LINEAR_UNITS = inch"),
            "[TRAJ]LINEAR_UNITS = 'inch'; compgate writes mm",
        ),
        (
            (
                "machine.ini",
                "[AXIS_Z]\nOFFSET_AV_RATIO = 0.1\n",
                "[AXIS_Z]\n",
            ),
            "[AXIS_Z]OFFSET_AV_RATIO is missing from the INI file",
        ),
        (
            (
                "machine.hal",
                "net j0-homed joint.0.homed\n",
                "net j0-homed joint.0.homed\nnet z-offset axis.z.eoffset-counts\n",
            ),
            "axis.z.eoffset-counts is on signal z-offset already",
        ),
        (
            (
                "machine.ini",
                "[COMPGATE_Z]\nJOINT = 2",
                "[COMPGATE_Z]\nJOINT = 7",
            ),
            "LinuxCNC has no pin joint.7.homed: check [COMPGATE_Z]JOINT = 7",
        ),
        (
            ("machine.ini", "AXES = X Z", "AXES = X, Z"),
            "[COMPGATE]AXES = X, Z: expected axis letters separated by spaces",
        ),
        (
            (
                "machine.ini",
                "AXES = X Z",
                "AXES = X Z A\n\n[COMPGATE_A]\nJOINT = 0\nPORT = 0\nMD32750 = 3",
            ),
            "axis A in [COMPGATE]AXES is not in [TRAJ]COORDINATES = XYZ",
        ),
        (
            (
                "machine.ini",
                "[COMPGATE_Z]\nJOINT = 2\nPORT = 0\n",
                z_port.as_str(),
            ),
            z_port_error.as_str(),
        ),
        (
            (
                "compgate-nc-z.json",
                "",
                r#"{"SD43900": 20.0, "SD43910": 0.0, "SD43920": 0.0}"#,
            ),
            "setting data file compgate-nc-z.json: SD43900 = 20.0 is not a number within +-10.0",
        ),
        (
            ("compgate-nc-x.json", "", "{\"SD43900\": 0.0"),
            "setting data file compgate-nc-x.json: Expecting",
        ),
    ] {
        let Some(cnc) = LinuxCnc::launch(Some(edit)) else {
            return;
        };
        let logs = cnc.exit_logs();
        assert!(logs.contains(expected), "{expected}\n{logs}");
    }
}
