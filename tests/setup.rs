//! `deploy/setup.sh`'s choice of a mirror for the bookworm-backports source, run against apt
//! directories made up for each case: it must take the machine's own Debian mirror, in the
//! format of the entry it came from, and find none rather than invent one.

use std::path::Path;
use std::process::Command;

use pointfarm_tests::run_ok;

/// Runs one of the script's functions with `args`, returning its standard output.
fn setup_function(function: &str, args: &[&str]) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/setup.sh");
    let mut bash = Command::new("bash");
    bash.arg("-c")
        // $0 is not the script, so sourcing it defines its functions without running it.
        .arg(format!("source \"$1\"; shift; {function} \"$@\""))
        .arg("pointfarm-setup-test")
        .arg(&script)
        .args(args);
    let output = run_ok(&mut bash, function);
    String::from_utf8(output.stdout).expect("UTF-8 output")
}

fn apt_dir(files: &[(&str, &str)]) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("temp dir");
    std::fs::create_dir(dir.path().join("sources.list.d")).expect("sources.list.d");
    for (name, text) in files {
        std::fs::write(dir.path().join(name), text).expect("write a sources file");
    }
    dir
}

fn mirror_of(dir: &tempfile::TempDir) -> String {
    let path = dir.path().to_str().expect("UTF-8 path");
    setup_function("debian_mirror", &[path]).trim().to_string()
}

#[test]
fn one_line_sources_give_the_bookworm_entry_of_the_main_archive() {
    let dir = apt_dir(&[(
        "sources.list",
        "# deb http://commented.example/debian bookworm main\n\
         deb cdrom:[Debian 12]/ bookworm main\n\
         deb-src http://src.example/debian bookworm main\n\
         deb http://security.example/debian-security bookworm-security main\n\
         deb [arch=amd64 signed-by=/usr/share/keyrings/k.gpg] http://mirror.example/debian bookworm main contrib\n",
    )]);
    assert_eq!(
        mirror_of(&dir),
        "list http://mirror.example/debian /usr/share/keyrings/k.gpg"
    );
}

#[test]
fn deb822_sources_skip_disabled_paragraphs_and_the_security_archive() {
    let dir = apt_dir(&[(
        "sources.list.d/debian.sources",
        "Types: deb\nURIs: http://disabled.example/debian\nSuites: bookworm\nComponents: main\nEnabled: no\n\n\
         Types: deb\nURIs: http://security.example/debian-security\nSuites: bookworm-security\nComponents: main\n\n\
         types: deb deb-src\nuris: http://mirror.example/debian\nsuites: bookworm bookworm-updates\n\
         components: main\nsigned-by: /usr/share/keyrings/debian-archive-keyring.gpg\n",
    )]);
    assert_eq!(
        mirror_of(&dir),
        "sources http://mirror.example/debian /usr/share/keyrings/debian-archive-keyring.gpg"
    );
}

#[test]
fn no_debian_mirror_is_invented() {
    let only_security = apt_dir(&[(
        "sources.list",
        "deb http://security.example/debian-security bookworm-security main\n",
    )]);
    assert_eq!(mirror_of(&only_security), "");
    let empty = apt_dir(&[]);
    assert_eq!(mirror_of(&empty), "");
}

#[test]
fn the_backports_source_is_written_in_the_style_of_its_mirror() {
    let dir = apt_dir(&[]);
    // What the script writes for the mirror line `mirror`, as it reads back.
    let written_for = |mirror: &str| {
        let path = dir.path().to_str().expect("UTF-8 path");
        let written = setup_function("write_backports_source", &[mirror, path, ""]);
        std::fs::read_to_string(written.trim()).expect("the written source")
    };
    assert_eq!(
        written_for("sources http://mirror.example/debian /k.gpg"),
        "Types: deb\nURIs: http://mirror.example/debian\nSuites: bookworm-backports\n\
         Components: main\nSigned-By: /k.gpg\n"
    );
    assert_eq!(
        written_for("list http://mirror.example/debian -"),
        "deb http://mirror.example/debian bookworm-backports main\n"
    );
}
