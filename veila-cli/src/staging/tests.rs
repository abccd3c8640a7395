use super::*;

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn inputs_are_recognised_by_identity() {
    let d = tempfile::tempdir().unwrap();
    let a = d.path().join("a.bin");
    std::fs::write(&a, b"1").unwrap();
    let mut inputs = Inputs::new();
    inputs.add(&a);
    let other = d.path().join(".").join("sub/../a.bin");
    std::fs::create_dir(d.path().join("sub")).unwrap();
    assert!(inputs.check_output(&other).is_err());
    #[cfg(unix)]
    {
        std::fs::hard_link(&a, d.path().join("hard.bin")).unwrap();
        assert!(inputs.check_output(&d.path().join("hard.bin")).is_err());
    }
    assert!(inputs.check_output(&d.path().join("new.bin")).is_ok());
}

#[test]
fn errors_name_the_output_not_the_staging_folder() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("result");
    let staged = stage_output(&out, false, &Inputs::new(), "generate").unwrap();
    let hidden = staged.path().join("scan_000.bin");
    let err = anyhow::anyhow!("{}: No space left on device", hidden.display());
    drop(staged);
    let msg = explain(err).to_string();
    assert!(
        msg.contains(&out.join("scan_000.bin").display().to_string()),
        "{msg}"
    );
    assert!(!msg.contains(".veila-staging"), "{msg}");
    // the staging folder and the lock went with the failed command
    assert_eq!(names(d.path()), Vec::<String>::new());
}

fn publish(out: &Path, command: &str, files: &[(&str, &str)]) -> Result<()> {
    let staged = stage_output(out, true, &Inputs::new(), command)?;
    for (n, text) in files {
        let p = staged.path().join(n);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    }
    staged.commit()
}

#[test]
fn force_replaces_the_commands_own_files_only() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("o");
    publish(
        &out,
        "generate",
        &[
            ("scan_000.bin", "g0"),
            ("scan_001.bin", "g1"),
            ("generate.json", "g"),
        ],
    )
    .unwrap();
    // the user's files, one named like an output
    std::fs::write(out.join("scan_2024_notes.txt"), "mine").unwrap();
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    // without --force a non-empty folder is refused
    let refused = stage_output(&out, false, &Inputs::new(), "generate")
        .unwrap_err()
        .to_string();
    assert!(refused.contains("--force"), "{refused}");
    // a smaller run drops its stale scan and keeps everything else
    publish(
        &out,
        "generate",
        &[("scan_000.bin", "G0"), ("generate.json", "G")],
    )
    .unwrap();
    assert_eq!(
        names(&out),
        [
            MANIFEST,
            "generate.json",
            "notes.txt",
            "scan_000.bin",
            "scan_2024_notes.txt"
        ]
    );
    assert_eq!(
        std::fs::read_to_string(out.join("scan_000.bin")).unwrap(),
        "G0"
    );
    // another command never replaces generate's files, and drops none of them
    let e = publish(&out, "edit", &[("scan_000.bin", "E"), ("edit.json", "e")])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("scan_000.bin") && e.contains("veila edit"),
        "{e}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("scan_000.bin")).unwrap(),
        "G0"
    );
    publish(&out, "edit", &[("edit.json", "e")]).unwrap();
    publish(&out, "edit", &[("edit2.json", "e")]).unwrap();
    assert_eq!(
        names(&out),
        [
            MANIFEST,
            "edit2.json",
            "generate.json",
            "notes.txt",
            "scan_000.bin",
            "scan_2024_notes.txt"
        ]
    );
    // nor does it write over the user's file
    let e = publish(&out, "generate", &[("notes.txt", "x")])
        .unwrap_err()
        .to_string();
    assert!(e.contains("notes.txt"), "{e}");
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
    // nothing is left beside the output
    assert_eq!(names(d.path()), ["o"]);
    let m = read_manifest(&out).unwrap();
    assert_eq!(m.commands["generate"].len(), 2);
    assert_eq!(
        m.commands["edit"].iter().collect::<Vec<_>>(),
        ["edit2.json"]
    );
}

#[test]
fn a_rerun_with_fewer_frames_leaves_no_stale_frames_in_subfolders() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("sim");
    publish(
        &out,
        "simulate",
        &[
            ("velodyne/0.bin", "a"),
            ("velodyne/1.bin", "b"),
            ("poses.txt", "2"),
        ],
    )
    .unwrap();
    std::fs::write(out.join("velodyne/user.txt"), "mine").unwrap();
    publish(
        &out,
        "simulate",
        &[("velodyne/0.bin", "A"), ("poses.txt", "1")],
    )
    .unwrap();
    assert_eq!(names(&out.join("velodyne")), ["0.bin", "user.txt"]);
}

#[test]
fn a_second_writer_of_one_folder_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("o");
    let first = stage_output(&out, true, &Inputs::new(), "generate").unwrap();
    let e = stage_output(&d.path().join("./o"), true, &Inputs::new(), "generate")
        .unwrap_err()
        .to_string();
    assert!(e.contains("another veila process"), "{e}");
    // and file outputs into that folder wait for no one: they are refused too
    std::fs::create_dir(&out).unwrap();
    let e = publish_files(
        &[(out.join("a.txt"), b"1".to_vec())],
        &Inputs::new(),
        true,
        false,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("another veila process"), "{e}");
    std::fs::remove_dir(&out).unwrap();
    std::fs::write(first.path().join("f"), "x").unwrap();
    first.commit().unwrap();
    assert_eq!(names(d.path()), ["o"]);
}

#[test]
fn publish_is_all_or_nothing() {
    let d = tempfile::tempdir().unwrap();
    let a = d.path().join("a.txt");
    let b = d.path().join("b.txt");
    std::fs::write(&b, b"old").unwrap();
    let files = vec![(a.clone(), b"1".to_vec()), (b.clone(), b"2".to_vec())];
    let e = publish_files(&files, &Inputs::new(), false, false).unwrap_err();
    assert!(e.to_string().contains("b.txt"), "{e}");
    assert!(!a.exists());
    assert_eq!(std::fs::read(&b).unwrap(), b"old");
    publish_files(&files, &Inputs::new(), true, false).unwrap();
    assert_eq!(std::fs::read(&b).unwrap(), b"2");
    assert_eq!(names(d.path()), ["a.txt", "b.txt"]);
}

#[test]
fn partial_files_of_a_killed_owner_go_under_the_lock() {
    let d = tempfile::tempdir().unwrap();
    let ck = d.path().join("run/checkpoints");
    std::fs::create_dir_all(ck.join(".step-0000000010.tmp-77")).unwrap();
    std::fs::create_dir_all(ck.join("step-0000000005")).unwrap();
    let held = lock_folder(&d.path().join("run")).unwrap();
    let n = remove_partial(&held, &ck, |n| n.contains(".tmp-")).unwrap();
    assert_eq!(n, 1);
    assert_eq!(names(&ck), ["step-0000000005"]);
}

#[cfg(unix)]
#[test]
fn an_outputs_record_linked_to_dev_zero_is_refused_unread() {
    let d = tempfile::tempdir().unwrap();
    assert!(read_manifest(d.path()).unwrap().commands.is_empty());
    std::os::unix::fs::symlink("/dev/zero", d.path().join(MANIFEST)).unwrap();
    let e = format!("{:#}", read_manifest(d.path()).unwrap_err());
    assert!(
        e.contains(MANIFEST) && e.contains("not a regular file (a character device)"),
        "{e}"
    );
}

#[cfg(unix)]
#[test]
fn force_never_replaces_a_fifo_or_a_device_with_a_file() {
    use std::os::unix::fs::FileTypeExt;
    let d = tempfile::tempdir().unwrap();
    let fifo = d.path().join("report.json");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    if !made.is_ok_and(|s| s.success()) {
        eprintln!("skipped: `mkfifo` is not available to make the FIFO");
        return;
    }
    let files = vec![(fifo.clone(), b"{}".to_vec())];
    for force in [false, true] {
        let e = publish_files(&files, &Inputs::new(), force, false).unwrap_err();
        assert!(
            e.to_string().contains("is a FIFO, not a regular file"),
            "{e}"
        );
        let t = std::fs::symlink_metadata(&fifo).unwrap().file_type();
        assert!(t.is_fifo(), "the FIFO is still there");
    }
    // the kind of a character device is named without touching it
    assert_eq!(
        special_file_kind(Path::new("/dev/null")),
        Some("a character device")
    );
    assert_eq!(special_file_kind(d.path()), None);
    assert_eq!(special_file_kind(&d.path().join("absent")), None);
}
