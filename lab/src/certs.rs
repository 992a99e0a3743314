//! Certificates for trying the shipped mutual-TLS Zenoh configuration (`rangegp certs`): a CA,
//! the daemon's certificate and one per planner, as `deploy/zenoh-*.json5` expects them.
//! Made with `rcgen`; for trials and tests; a production site uses its own PKI.

use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair, KeyUsagePurpose};
use std::path::Path;
use thiserror::Error;

/// A certificate could not be made or written.
#[derive(Debug, Error)]
pub enum CertError {
    /// rcgen refused the parameters or the key.
    #[error("cannot make the certificate")]
    Make(#[from] rcgen::Error),
    /// The file could not be written.
    #[error("cannot write the certificate")]
    Write(#[from] std::io::Error),
}

/// A certificate authority that signs leaf certificates into a directory.
pub struct Authority {
    issuer: Issuer<'static, KeyPair>,
}

impl Authority {
    /// A new CA named `name`; writes its certificate to `<dir>/<name>.pem`.
    pub fn new(dir: &Path, name: &str) -> Result<Self, CertError> {
        let mut params = CertificateParams::new(Vec::new())?;
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.distinguished_name.push(DnType::CommonName, name);
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::DigitalSignature];
        let key = KeyPair::generate()?;
        let cert = params.self_signed(&key)?;
        std::fs::write(dir.join(format!("{name}.pem")), cert.pem())?;
        Ok(Self {
            issuer: Issuer::new(params, key),
        })
    }

    /// Writes `<file>.pem` and `<file>.key`: a leaf for `localhost` with common name `cn`.
    pub fn leaf(&self, dir: &Path, file: &str, cn: &str) -> Result<(), CertError> {
        let mut params = CertificateParams::new(vec!["localhost".to_owned()])?;
        params.distinguished_name.push(DnType::CommonName, cn);
        params.use_authority_key_identifier_extension = true;
        let key = KeyPair::generate()?;
        let cert = params.signed_by(&key, &self.issuer)?;
        std::fs::write(dir.join(format!("{file}.pem")), cert.pem())?;
        std::fs::write(dir.join(format!("{file}.key")), key.serialize_pem())?;
        Ok(())
    }
}

/// Writes `ca.pem`, `rangegpd.pem` / `.key` (for `localhost`) and `<name>.pem` / `.key` for
/// each planner (common name `name`) into `dir`.
pub fn write_site(dir: &Path, planners: &[String]) -> Result<(), CertError> {
    std::fs::create_dir_all(dir)?;
    let ca = Authority::new(dir, "ca")?;
    ca.leaf(dir, "rangegpd", "rangegpd")?;
    for name in planners {
        ca.leaf(dir, name, name)?;
    }
    Ok(())
}
