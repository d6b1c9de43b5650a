//! The browser transport's flags and settings, apart from
//! [`crate::config`] so that the CLI only flattens them in (and that file
//! stays about gRPC).
//!
//! The socket limits are deliberately not new flags: a WebSocket is a TCP
//! connection like a gRPC one, so `--max-connections`,
//! `--max-connections-per-peer` and `--max-message-bytes` bound it too,
//! and the session limits (`--max-sessions-per-client`, in-flight frames,
//! `--open-timeout`) apply because it runs the same stream handler.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// Where the page is built (`cd web && npm ci`), relative
/// to the directory the server starts in.
pub const DEFAULT_WEB_DIR: &str = "web/dist";

/// How long a WebSocket may stay silent (no message, not even the pong to
/// the server's ping) before the server closes it, and how long one answer
/// may take to be written to a browser that does not read.
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(30);

/// The browser transport's flags (flattened into [`crate::Cli`]).
#[derive(Debug, Clone, clap::Args)]
pub struct WebArgs {
    /// Serve the browser transport on this address: the live page at / and a WebSocket
    /// at /v1/stream carrying the Stream RPC's messages (one binary message = one
    /// protobuf). Off by default. Plain HTTP: for anything but localhost, put it behind
    /// a TLS proxy (browsers allow the camera only on https:// or localhost).
    #[arg(long, env = "BLAPOSE_WEB_ADDR", value_name = "HOST:PORT")]
    pub web_addr: Option<SocketAddr>,

    /// With --web-addr: the built page served at / (build it with
    /// `cd web && npm ci`).
    #[arg(long, env = "BLAPOSE_WEB_DIR", value_name = "DIR", default_value = DEFAULT_WEB_DIR)]
    pub web_dir: PathBuf,
}

impl WebArgs {
    /// The settings these flags ask for (`None`: no browser transport).
    pub fn into_config(self) -> Option<WebConfig> {
        self.web_addr.map(|addr| WebConfig {
            addr,
            dir: self.web_dir,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
        })
    }
}

/// The browser transport's settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WebConfig {
    /// The HTTP listen address (port 0: any free port, see
    /// [`crate::ServerHandle::web_addr`]).
    pub addr: SocketAddr,
    /// The built page; when it is missing `/` says how to build it.
    pub dir: PathBuf,
    /// A socket silent this long is closed; the server pings it every
    /// third of it, so a live browser (which answers pings by itself)
    /// never is. Also the longest one write may block.
    pub idle_timeout: Duration,
}

impl WebConfig {
    /// The transport on `addr` with the defaults.
    pub fn new(addr: SocketAddr) -> Self {
        Self {
            addr,
            dir: PathBuf::from(DEFAULT_WEB_DIR),
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
        }
    }

    /// How often the server pings a socket.
    pub fn ping_interval(&self) -> Duration {
        (self.idle_timeout / 3).max(Duration::from_millis(10))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[test]
    fn the_browser_transport_is_off_unless_asked() {
        let cli = crate::Cli::try_parse_from(["blapose-server"]).unwrap();
        assert_eq!(cli.into_config().web, None);
        let cli =
            crate::Cli::try_parse_from(["blapose-server", "--web-addr", "127.0.0.1:8080"]).unwrap();
        let web = cli.into_config().web.expect("on with --web-addr");
        assert_eq!(web, WebConfig::new("127.0.0.1:8080".parse().unwrap()));
        assert_eq!(web.dir, PathBuf::from("web/dist"));
        assert_eq!(web.ping_interval(), Duration::from_secs(10));
        let cli = crate::Cli::try_parse_from([
            "blapose-server",
            "--web-addr",
            "0.0.0.0:0",
            "--web-dir",
            "/srv/page",
        ])
        .unwrap();
        assert_eq!(
            cli.into_config().web.map(|w| w.dir),
            Some(PathBuf::from("/srv/page"))
        );
        assert!(crate::Cli::try_parse_from(["blapose-server", "--web-addr", "8080"]).is_err());
    }
}
