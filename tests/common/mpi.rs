//! Launching the real binary under `mpirun` for the MPI tests, and reaching one of its ranks:
//! oversubscribed (more ranks than cores), loopback and shared-memory transports only, allowed
//! to run as root (CI containers).

use super::process;
use std::process::Command;

/// `mpirun` and the flags every MPI test launches `ranks` ranks with (the program follows).
pub fn launcher(ranks: usize) -> Vec<String> {
    [
        "mpirun",
        "-n",
        &ranks.to_string(),
        "--oversubscribe",
        "--mca",
        "btl",
        "self,vader",
        "--mca",
        "btl_vader_single_copy_mechanism",
        "none",
    ]
    .map(String::from)
    .to_vec()
}

/// The environment that lets `mpirun` run as root (CI containers).
pub const AS_ROOT: [(&str, &str); 2] = [
    ("OMPI_ALLOW_RUN_AS_ROOT", "1"),
    ("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1"),
];

/// `mpirun -n ranks voxrad` with the flags and environment every MPI test uses; the caller adds
/// the arguments.
pub fn command(ranks: usize) -> Command {
    let launcher = launcher(ranks);
    let mut c = Command::new(&launcher[0]);
    c.args(&launcher[1..])
        .arg(env!("CARGO_BIN_EXE_voxrad"))
        .envs(AS_ROOT);
    c
}

/// Sends `signal` to rank `rank` of the job mpirun `launcher` runs (the child of mpirun whose
/// environment names that rank); returns its pid.
pub fn signal_rank(launcher: i32, rank: usize, signal: i32) -> i32 {
    let ranks = process::children_of(launcher);
    let wanted = rank.to_string();
    let pid = *ranks
        .iter()
        .find(|&&p| process::env_of(p, "OMPI_COMM_WORLD_RANK").as_deref() == Some(&wanted))
        .unwrap_or_else(|| panic!("no rank {rank} among {ranks:?}"));
    // SAFETY: kill(2) on a process this test started (through mpirun).
    unsafe {
        libc::kill(pid, signal);
    }
    pid
}
