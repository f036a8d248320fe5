//! deploy/: `install.sh` run for real in a scratch root (a private mount namespace with
//! copies over /etc, /usr/local, /var/lib and /var/log, `cargo` and `systemctl`
//! stubbed), the unit's reload, and the docs that must agree with the status page.

// Test helpers: a panic with the message is the wanted failure.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const REPO: &str = env!("CARGO_MANIFEST_DIR");
const BIN: &str = env!("CARGO_BIN_EXE_compgate");

/// A scratch root for `install.sh`: what it installs lands in `root`, what it asks
/// systemctl is in `systemctl.log`.
struct Scratch {
    dir: tempfile::TempDir,
}

impl Scratch {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let sh = |script: &str| {
            let st = Command::new("sh")
                .args(["-c", script, "sh"])
                .arg(d)
                .arg(REPO)
                .arg(BIN)
                .status()
                .unwrap();
            assert!(st.success(), "{script}");
        };
        // The repository as install.sh needs it; /etc copied, so that useradd and
        // install -g compgate work on the copy.
        sh(r#"set -e; cd "$1"
            mkdir -p repo/deploy repo/config usrlocal/bin usrlocal/share varlib varlog shims state
            cp "$2/deploy/install.sh" "$2/deploy/compgate.service" repo/deploy/
            cp "$2/config/example.toml" repo/config/
            cp "$2/README.md" repo/
            cp -r "$2/docs" repo/
            cp -a /etc etc"#);
        // cargo: the test's build stands in for the production one.
        std::fs::write(
            d.join("shims/cargo"),
            format!(
                "#!/bin/sh\nmkdir -p target/production/release && cp '{BIN}' target/production/release/compgate\n"
            ),
        )
        .unwrap();
        // systemctl: logs its arguments; the unit is active once (re)started.
        std::fs::write(
            d.join("shims/systemctl"),
            format!(
                "#!/bin/sh\necho \"$*\" >> '{log}'\ncase \"$1\" in\n  is-active) test -e '{active}' ;;\n  start|restart) touch '{active}' ;;\nesac\n",
                log = d.join("systemctl.log").display(),
                active = d.join("state/active").display()
            ),
        )
        .unwrap();
        sh(r#"chmod +x "$1/shims/cargo" "$1/shims/systemctl""#);
        Scratch { dir }
    }

    fn path(&self, p: &str) -> PathBuf {
        self.dir.path().join(p)
    }

    /// Runs `install.sh args` in the scratch root.
    fn install(&self, args: &[&Path]) -> Output {
        self.install_from(Path::new("/"), args)
    }

    /// As [`Self::install`], run from the directory `cwd`.
    fn install_from(&self, cwd: &Path, args: &[&Path]) -> Output {
        let path = std::env::var("PATH").unwrap_or_default();
        self.run_install(cwd, args, &path, None)
    }

    /// As [`Self::install`] on a PC without Rust, through `sudo` by `sudo_user` (who
    /// has no cargo either): the binary is what `repo/target/production/release`
    /// holds, copied there from another machine.
    fn install_without_cargo(&self, sudo_user: &str, args: &[&Path]) -> Output {
        std::fs::remove_file(self.path("shims/cargo")).unwrap();
        self.run_install(
            Path::new("/"),
            args,
            "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
            Some(sudo_user),
        )
    }

    fn run_install(
        &self,
        cwd: &Path,
        args: &[&Path],
        path: &str,
        sudo_user: Option<&str>,
    ) -> Output {
        let d = self.dir.path();
        let script = r#"d=$1; shift
            mount --bind "$d/etc" /etc && mount --bind "$d/usrlocal" /usr/local \
            && mount --bind "$d/varlib" /var/lib && mount --bind "$d/varlog" /var/log \
            && exec bash "$d/repo/deploy/install.sh" "$@""#;
        let path = format!("{}:{path}", d.join("shims").display());
        let mut cmd = Command::new("unshare");
        match sudo_user {
            Some(user) => cmd.env("SUDO_USER", user),
            None => cmd.env_remove("SUDO_USER"),
        };
        cmd.args([
            "--mount",
            "--propagation",
            "private",
            "sh",
            "-c",
            script,
            "sh",
        ])
        .arg(d)
        .args(args)
        .current_dir(cwd)
        .env("PATH", path)
        .output()
        .expect("unshare runs (util-linux; a mount namespace needs root)")
    }

    /// What systemctl was asked since the last call.
    fn systemctl(&self) -> Vec<String> {
        let log = self.path("systemctl.log");
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        let _ = std::fs::remove_file(&log);
        text.lines().map(str::to_string).collect()
    }

    /// The installed config and the backups beside it.
    fn configs(&self) -> (String, Vec<PathBuf>) {
        let dir = self.path("etc/compgate");
        let config = std::fs::read_to_string(dir.join("compgate.toml")).unwrap();
        let mut backups: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.file_name().unwrap() != "compgate.toml")
            .collect();
        backups.sort();
        (config, backups)
    }
}

fn text(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr)
}

fn assert_ok(out: &Output) -> String {
    let t = text(out);
    assert!(out.status.success(), "{}\n{t}", out.status);
    t
}

// Installing, then updating: a config given that differs from the installed one is
// refused with the difference unless --replace-config says to replace it (the old one
// kept as a dated backup), the config that will run is validated before anything is
// installed, and a running service is restarted on the new binary; each step says what
// it did.
#[test]
fn install_sh_installs_updates_and_says_what_it_did() {
    let s = Scratch::new();
    let example = std::fs::read_to_string(s.path("repo/config/example.toml")).unwrap();
    let plant = s.path("plant.toml");
    std::fs::write(
        &plant,
        example.replace("status_interval_s = 1.0", "status_interval_s = 2.0"),
    )
    .unwrap();

    // First install: the example config, the service started.
    let out = assert_ok(&s.install(&[]));
    assert!(
        out.contains("installed config/example.toml as /etc/compgate/compgate.toml"),
        "{out}"
    );
    assert!(out.contains("starting compgate"), "{out}");
    assert_eq!(
        s.systemctl()[..4],
        [
            "enable --no-reload compgate.service",
            "daemon-reload",
            "is-active --quiet compgate.service",
            "restart compgate.service"
        ]
    );
    assert_eq!(s.configs(), (example.clone(), vec![]));
    assert!(s.path("usrlocal/bin/compgate").exists());

    // Update with the plant's config: refused, with the difference and the ways on;
    // nothing installed, nothing restarted.
    let out = s.install(&[&plant]);
    let t = text(&out);
    assert!(!out.status.success(), "{t}");
    assert!(
        t.contains(&format!(
            "the installed /etc/compgate/compgate.toml differs from {}:",
            plant.display()
        )),
        "{t}"
    );
    assert!(
        t.contains("\n-status_interval_s = 1.0\n+status_interval_s = 2.0\n"),
        "{t}"
    );
    assert!(t.contains("update and keep the installed config:"), "{t}");
    assert!(
        t.contains(&format!(
            "install.sh --replace-config {}\n",
            plant.display()
        )),
        "{t}"
    );
    assert_eq!(s.configs(), (example.clone(), vec![]));
    assert_eq!(s.systemctl(), Vec::<String>::new());

    // With --replace-config: the old one is kept, the new one runs.
    let out = assert_ok(&s.install(&[Path::new("--replace-config"), &plant]));
    assert!(
        out.contains(&format!(
            "replaced /etc/compgate/compgate.toml with {}; the previous one is /etc/compgate/compgate.toml.",
            plant.display()
        )),
        "{out}"
    );
    assert!(
        out.contains("compgate was running: restarting it on the new binary and config"),
        "{out}"
    );
    assert!(s
        .systemctl()
        .contains(&"restart compgate.service".to_string()));
    let (config, backups) = s.configs();
    assert_eq!(config, std::fs::read_to_string(&plant).unwrap());
    assert_eq!(backups.len(), 1, "{backups:?}");
    assert_eq!(std::fs::read_to_string(&backups[0]).unwrap(), example);

    // The same config again, and none: nothing replaced, still validated, restarted.
    // A relative path is taken from where the script is run, not from the repository.
    let out = assert_ok(&s.install_from(&s.path(""), &[Path::new("plant.toml")]));
    assert!(
        out.contains(&format!(
            "/etc/compgate/compgate.toml is already {}: unchanged",
            plant.display()
        )),
        "{out}"
    );
    let out = assert_ok(&s.install(&[]));
    assert!(
        out.contains("kept the installed /etc/compgate/compgate.toml"),
        "{out}"
    );
    assert!(out.contains("/etc/compgate/compgate.toml: OK"), "{out}");
    assert_eq!(s.configs().1.len(), 1);
    s.systemctl();

    // A config that does not validate: nothing installed, nothing restarted.
    let bad = s.path("bad.toml");
    std::fs::write(
        &bad,
        example.replace("status_interval_s = 1.0", "status_intervall_s = 1.0"),
    )
    .unwrap();
    let out = s.install(&[Path::new("--replace-config"), &bad]);
    let t = text(&out);
    assert!(!out.status.success(), "{t}");
    assert!(t.contains("gateway.status_intervall_s: unknown key"), "{t}");
    assert!(
        t.contains("does not validate: nothing installed, the service is as it was"),
        "{t}"
    );
    assert_eq!(s.configs().0, std::fs::read_to_string(&plant).unwrap());
    assert_eq!(s.systemctl(), Vec::<String>::new());
}

// validate runs outside the unit's sandbox, so a database outside the state directory
// that the user compgate may write passes it; under ProtectSystem=strict, ProtectHome
// and PrivateTmp it would not be written (or be lost at each stop). install.sh
// (through validate) warns.
/// Places `bin` where a binary built on another machine is copied to.
fn place_binary(s: &Scratch, bin: &[u8]) {
    let dir = s.path("repo/target/production/release");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("compgate"), bin).unwrap();
    Command::new("chmod")
        .arg("+x")
        .arg(dir.join("compgate"))
        .status()
        .unwrap();
}

// On a PC without Rust, `sudo deploy/install.sh` tried to build as the user who called
// sudo, who had no cargo either, and stopped at "cargo: command not found" (exit 127)
// instead of installing the binary copied there.
#[test]
fn install_sh_under_sudo_without_cargo_installs_the_copied_binary() {
    let s = Scratch::new();
    place_binary(&s, &std::fs::read(BIN).unwrap());
    let t = assert_ok(&s.install_without_cargo("nobody", &[]));
    assert!(
        t.contains("install.sh: cargo not found; installing target/production/release/compgate as built before"),
        "{t}"
    );
    assert!(s.path("usrlocal/bin/compgate").exists(), "{t}");
}

// A binary for another CPU (an x86 build on an ARM box, an aarch64 one on a 32-bit ARM
// userland) was reported as a config that does not validate.
#[test]
fn install_sh_names_a_binary_built_for_another_machine() {
    let s = Scratch::new();
    let mut foreign = std::fs::read(BIN).unwrap();
    // e_machine: aarch64 (0xB7) here on x86-64, x86-64 (0x3E) on an aarch64 host.
    let other: (u8, &str) = if cfg!(target_arch = "aarch64") {
        (0x3E, "x86_64")
    } else {
        (0xB7, "aarch64")
    };
    foreign[18..20].copy_from_slice(&[other.0, 0]);
    place_binary(&s, &foreign);
    let out = s.install_without_cargo("nobody", &[]);
    let t = text(&out);
    assert!(!out.status.success(), "{t}");
    assert!(
        t.contains("does not run on this machine")
            && t.contains(&format!("it is built for {}", other.1)),
        "{t}"
    );
    assert!(!t.contains("does not validate"), "{t}");
    assert!(!s.path("usrlocal/bin/compgate").exists(), "{t}");
}

#[test]
fn install_sh_warns_of_a_database_outside_the_state_directory() {
    use std::os::unix::fs::PermissionsExt;
    let s = Scratch::new();
    let example = std::fs::read_to_string(s.path("repo/config/example.toml")).unwrap();
    let outside = s.path("outside");
    std::fs::create_dir(&outside).unwrap();
    // Writable for the user compgate, as which install.sh validates.
    let mode = |p: &Path, m: u32| std::fs::set_permissions(p, std::fs::Permissions::from_mode(m));
    mode(&s.path(""), 0o711).unwrap();
    mode(&outside, 0o1777).unwrap();
    let plant = s.path("plant.toml");
    let db = outside.join("compgate.db");
    std::fs::write(
        &plant,
        format!(
            "{example}\n[recorder]\npath = {:?}\n",
            db.display().to_string()
        ),
    )
    .unwrap();
    let out = assert_ok(&s.install(&[&plant]));
    assert!(
        out.contains(&format!(
            "warning: {}: recorder.path: the database {} is outside the state directory /var/lib/compgate",
            plant.display(),
            db.display()
        )),
        "{out}"
    );
    // A relative path is in the state directory: no warning.
    std::fs::write(
        &plant,
        format!("{example}\n[recorder]\npath = \"compgate.db\"\n"),
    )
    .unwrap();
    let out = assert_ok(&s.install(&[Path::new("--replace-config"), &plant]));
    assert!(!out.contains("outside the state directory"), "{out}");
}

// install.sh validates as the user compgate, as the unit runs: a database that user
// cannot write (root's, from a `compgate run` by hand) fails before anything is
// installed, instead of at the restart after the old binary is gone.
#[test]
fn install_sh_refuses_a_database_the_service_user_cannot_write() {
    let s = Scratch::new();
    let example = std::fs::read_to_string(s.path("repo/config/example.toml")).unwrap();
    assert_ok(&s.install(&[]));
    s.systemctl();
    let db = s.path("varlib/compgate/compgate.db");
    std::fs::write(&db, "").unwrap(); // root's, 0644
    let plant = s.path("plant.toml");
    std::fs::write(
        &plant,
        format!("{example}\n[recorder]\npath = \"compgate.db\"\n"),
    )
    .unwrap();
    let out = s.install(&[Path::new("--replace-config"), &plant]);
    let t = text(&out);
    assert!(!out.status.success(), "{t}");
    assert!(
        t.contains(&format!(
            "{}: recorder.path: /var/lib/compgate/compgate.db: the database is not writable: Permission denied",
            plant.display()
        )),
        "{t}"
    );
    assert!(t.contains("does not validate: nothing installed"), "{t}");
    assert_eq!(s.configs(), (example, vec![]));
    assert_eq!(s.systemctl(), Vec::<String>::new());
}

// `systemctl reload` validates before it signals: a config that does not validate
// fails the reload with its problems, and the service is never sent SIGHUP.
#[test]
fn the_unit_validates_before_it_signals_a_reload() {
    let unit = std::fs::read_to_string(format!("{REPO}/deploy/compgate.service")).unwrap();
    let reload: Vec<&str> = unit
        .lines()
        .filter(|l| l.starts_with("ExecReload="))
        .collect();
    assert_eq!(
        reload,
        [
            "ExecReload=/usr/local/bin/compgate validate --config /etc/compgate/compgate.toml",
            "ExecReload=/bin/kill -HUP $MAINPID"
        ]
    );
    // systemd finds nothing wrong with the unit but the binary not installed here.
    let out = Command::new("systemd-analyze")
        .args(["verify", &format!("{REPO}/deploy/compgate.service")])
        .output()
        .expect("systemd-analyze runs (./test.sh installs the systemd package)");
    let t = text(&out);
    for line in t.lines() {
        assert!(
            line.contains("/usr/local/bin/compgate is not executable"),
            "systemd-analyze verify: {line}\n{t}"
        );
    }
}

// The guide says how many NC jobs the status page lists: as many as page.js shows.
#[test]
fn the_guide_names_as_many_nc_jobs_as_the_status_page_shows() {
    let js = std::fs::read_to_string(format!("{REPO}/crates/service/src/page/page.js")).unwrap();
    let jobs = &js[js.find("function jobs(").unwrap()..];
    let n: usize = jobs[jobs.find("list.slice(0, ").unwrap() + 14..]
        .split(')')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let guide = std::fs::read_to_string(format!("{REPO}/docs/guide/commissioning.md")).unwrap();
    let guide = guide.split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(
        guide.contains(&format!("the last {n} NC jobs with their errors")),
        "the page shows {n} jobs; the guide says otherwise"
    );
}

// Field review: `DevicePolicy=closed` allowed only ttyUSB, ttyACM and ttyS, so the
// on-board RS-485 port of a Raspberry Pi (ttyAMA), an i.MX board (ttymxc), an
// SC16IS7xx HAT (ttySC) and the like could not be opened under the unit. Each group
// is allowed read-write, and the guide names every one of them.
#[test]
fn the_unit_allows_the_common_embedded_serial_ports_and_the_guide_names_them() {
    let unit = std::fs::read_to_string(format!("{REPO}/deploy/compgate.service")).unwrap();
    let allowed: Vec<&str> = unit
        .lines()
        .filter_map(|l| l.strip_prefix("DeviceAllow="))
        .collect();
    let groups = [
        "ttyUSB", "ttyACM", "ttyS", "ttyAMA", "ttymxc", "ttyLP", "ttyO", "ttySC", "ttyXR",
    ];
    let wanted: Vec<String> = groups.iter().map(|g| format!("char-{g} rw")).collect();
    assert_eq!(allowed, wanted, "{unit}");
    assert!(unit.contains("\nDevicePolicy=closed\n"), "{unit}");
    let guide = std::fs::read_to_string(format!("{REPO}/docs/deployment.md")).unwrap();
    for g in groups {
        assert!(guide.contains(&format!("`{g}`")), "docs/deployment.md: {g}");
    }
    assert!(
        guide.contains("`DeviceAllow=char-<group> rw`"),
        "docs/deployment.md: the drop-in"
    );
}

/// `(symbol, glibc version)` of the `GLIBC_x.y` symbols `objdump -T` lists for `path`:
/// the ones it needs (`undefined`) or the ones it defines.
fn glibc_symbols(path: &Path, undefined: bool) -> Vec<(String, (u32, u32))> {
    let out = Command::new("objdump")
        .arg("-T")
        .arg(path)
        .output()
        .expect("objdump (binutils) runs");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter(|l| l.contains("*UND*") == undefined)
        .filter_map(|l| {
            let (_, rest) = l.split_once("GLIBC_")?;
            let (version, name) = rest.split_once(char::is_whitespace)?;
            let mut v = version.trim_end_matches(')').split('.');
            let major = v.next()?.parse().ok()?;
            let minor = v.next()?.parse().ok()?;
            Some((name.trim().to_string(), (major, minor)))
        })
        .collect()
}

// The binary linked `mallinfo2`, new in glibc 2.33: it could not be built or started
// on glibc 2.31 (Debian 11, the base of several ARM gateway boxes' images). Every glibc
// symbol it needs must exist in a version no newer than 2.31 in this machine's
// libraries (a newer version of an old symbol is only what this machine links).
#[test]
fn the_binary_needs_nothing_glibc_2_31_lacks() {
    let bin = Path::new(BIN);
    let ldd = Command::new("ldd").arg(bin).output().expect("ldd runs");
    // `libc.so.6 => /lib/.../libc.so.6 (0x...)`, and the loader: `/lib64/ld-... (0x...)`.
    let libs: Vec<PathBuf> = String::from_utf8_lossy(&ldd.stdout)
        .lines()
        .filter_map(|l| {
            let path = l.rsplit("=> ").next()?.split_whitespace().next()?;
            path.starts_with('/').then(|| PathBuf::from(path))
        })
        .collect();
    assert!(!libs.is_empty(), "ldd found no libraries");
    let mut have: std::collections::HashMap<String, Vec<(u32, u32)>> = Default::default();
    for lib in &libs {
        for (name, v) in glibc_symbols(lib, false) {
            have.entry(name).or_default().push(v);
        }
    }
    let needed = glibc_symbols(bin, true);
    assert!(!needed.is_empty(), "objdump listed no glibc symbol");
    // Before 2.33 these came from libc_nonshared.a, linked into the binary by an older
    // glibc's libc.so: no shared symbol needed there.
    const LINKED_IN_BEFORE_2_33: [&str; 8] = [
        "stat",
        "fstat",
        "lstat",
        "fstatat",
        "stat64",
        "fstat64",
        "lstat64",
        "fstatat64",
    ];
    let newer: Vec<String> = needed
        .iter()
        .filter(|(name, _)| !LINKED_IN_BEFORE_2_33.contains(&name.as_str()))
        .filter(|(name, _)| {
            !have
                .get(name)
                .is_some_and(|vs| vs.iter().any(|v| *v <= (2, 31)))
        })
        .map(|(name, (a, b))| format!("{name}@GLIBC_{a}.{b}"))
        .collect();
    assert!(newer.is_empty(), "not in glibc 2.31: {newer:?}");
}
