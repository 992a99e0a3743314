//! The shipped production Zenoh configuration (deploy/zenoh-rangegpd.json5: router, one mutual-TLS
//! listener, access control denying by default) with certificates generated here: a planner whose
//! certificate is listed gets answers; a client with a certificate from another CA, and one
//! signed by the right CA but not listed, get none.

use anyhow::Result;
use rangegp_client::{Client, ClientError};
use rangegp_lab::certs::Authority;
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_tests::{unique_id, TempDir, WAIT};
use rangegp_transport::reserve_loopback_endpoint;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The shipped file with this test's certificate directory and port.
fn render(template: &str, tls_dir: &Path, port: &str, out: PathBuf) -> Result<PathBuf> {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../deploy")
            .join(template),
    )?
    .replace("/etc/rangegp/tls", &tls_dir.to_string_lossy())
    .replace("localhost:7447", &format!("localhost:{port}"));
    std::fs::write(&out, text)?;
    Ok(out)
}

/// A planner using `cert` (`<cert>.pem` / `.key` in `dir`) with the shipped planner config.
fn planner(dir: &Path, port: &str, map_id: &str, cert: &str) -> Result<Client> {
    let text = std::fs::read_to_string(render("zenoh-planner.json5", dir, port, dir.join("tmp.json5"))?)?
        .replace("planner.pem", &format!("{cert}.pem"))
        .replace("planner.key", &format!("{cert}.key"));
    let file = dir.join(format!("zenoh-{cert}.json5"));
    std::fs::write(&file, text)?;
    Ok(Client::builder(map_id)
        .config_file(file)
        .timeout(Duration::from_secs(2))
        .open()?)
}

#[test]
fn only_listed_certificates_get_answers() -> Result<()> {
    zenoh::init_log_from_env_or("error");
    let tmp = TempDir::new("tls")?;
    let dir = tmp.path();
    let ca = Authority::new(dir, "ca")?;
    ca.leaf(dir, "rangegpd", "rangegpd")?;
    ca.leaf(dir, "planner", "planner-1")?;
    ca.leaf(dir, "intruder", "intruder")?;
    let rogue = Authority::new(dir, "rogue-ca")?;
    rogue.leaf(dir, "forged", "planner-1")?;

    let reserved = reserve_loopback_endpoint()?;
    let port = reserved.port().to_string();
    let daemon_config = render(
        "zenoh-rangegpd.json5",
        dir,
        &port,
        dir.join("zenoh-rangegpd.json5"),
    )?;
    let mut config = Config {
        map_id: unique_id("tls"),
        ..Config::default()
    };
    config.checkpoint.enabled = false;
    config.ingest.service_name = format!("rangegp/{}/scans", unique_id("svc"));
    config.metrics.listen = String::new();
    config.zenoh.config_file = Some(daemon_config);
    let daemon = Daemon::builder(config.clone()).start()?;
    drop(reserved);
    let map_id = config.map_id.clone();

    let allowed = planner(dir, &port, &map_id, "planner")?;
    allowed.wait_for_daemon(WAIT)?;
    let status = allowed.status()?;
    assert_eq!(status.scans_received, 0);
    let refused = matches!(allowed.elevation(&[[1.0, 1.0]]), Err(ClientError::Server { .. }));
    assert!(refused, "an elevation query is answered (here: no map yet)");

    // Signed by the right CA but not listed: the session opens, queries go unanswered.
    let intruder = planner(dir, &port, &map_id, "intruder")?;
    assert!(
        intruder.wait_for_daemon(Duration::from_secs(2)).is_err(),
        "intruder saw the daemon"
    );
    let answer = intruder.status();
    assert!(
        matches!(answer, Err(ClientError::Timeout(_))),
        "intruder got {answer:?}"
    );

    // A certificate from another CA (same common name): no session with the daemon at all.
    match planner(dir, &port, &map_id, "forged") {
        Ok(forged) => {
            let answer = forged.status();
            assert!(answer.is_err(), "forged certificate got {answer:?}");
        }
        Err(e) => eprintln!("forged certificate refused at connect: {e}"),
    }
    // The listed planner is still served.
    assert_eq!(allowed.status()?.scans_received, 0);
    daemon.shutdown();
    Ok(())
}
