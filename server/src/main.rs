//! `blapose-server`: parse flags, set up logging, serve until SIGTERM/Ctrl-C.

use anyhow::Context;
use clap::Parser;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let cli = blapose_server::Cli::parse();
    if cli.health_check {
        let tls = cli.health_check_tls();
        let serving = blapose_server::probe_health(cli.addr, tls.as_ref()).await;
        match serving {
            Ok(true) => std::process::exit(0),
            Ok(false) => {
                eprintln!("{}: NOT_SERVING", cli.addr);
                std::process::exit(1)
            }
            Err(e) => {
                eprintln!("{}: {:#}", cli.addr, anyhow::Error::from(e));
                std::process::exit(1)
            }
        }
    }
    blapose_server::telemetry::init(cli.log_format)
        .map_err(|e| anyhow::anyhow!("cannot set up logging: {e}"))?;
    let addr = cli.addr;
    let config = cli.into_config();
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("cannot listen on {addr}"))?;
    blapose_server::serve(config, listener, blapose_server::shutdown::signal())
        .await
        .context("server failed")?;
    Ok(())
}
