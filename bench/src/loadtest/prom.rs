//! Reading the server's Prometheus endpoint: a minimal HTTP/1.1 GET and a
//! parser for the text exposition format.
//!
//! The load test only needs one page from a loopback address, so it speaks
//! just enough HTTP over a tokio `TcpStream` (one request, `Connection:
//! close`, identity or chunked body) instead of pulling in an HTTP client
//! crate. The parser reads the series the report needs (the batch-size
//! histogram, a few gauges) and ignores everything else, so new metrics on
//! the server never break it.

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Responses larger than this are refused (the server's page is ~10 KiB).
const MAX_RESPONSE_BYTES: usize = 16 * 1024 * 1024;

/// Why the metrics page could not be read.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// The URL is not `http://HOST:PORT[/PATH]`.
    #[error("metrics URL {0:?} is not of the form http://HOST:PORT/PATH")]
    BadUrl(String),
    /// Connecting, writing or reading failed.
    #[error("cannot fetch {url}: {source}")]
    Io {
        /// The URL.
        url: String,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// No complete answer within the deadline.
    #[error("fetching {url} timed out after {after:?}")]
    Timeout {
        /// The URL.
        url: String,
        /// The deadline.
        after: Duration,
    },
    /// The server answered, but not with a usable 200 response.
    #[error("{url}: {reason}")]
    Http {
        /// The URL.
        url: String,
        /// What was wrong.
        reason: String,
    },
}

/// `http://host:port/path`, split for the request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MetricsUrl {
    /// `host:port`, used to connect and as the `Host` header.
    pub authority: String,
    /// Path and query, starting with `/` (default `/metrics`).
    pub path: String,
}

impl MetricsUrl {
    /// Parse `http://HOST:PORT[/PATH]` (`/metrics` when no path is given).
    pub fn parse(url: &str) -> Result<Self, MetricsError> {
        let bad = || MetricsError::BadUrl(url.to_string());
        let rest = url.strip_prefix("http://").ok_or_else(bad)?;
        let (authority, path) = match rest.find('/') {
            Some(i) => (&rest[..i], &rest[i..]),
            None => (rest, "/metrics"),
        };
        let (host, port) = authority.rsplit_once(':').ok_or_else(bad)?;
        if host.is_empty() || port.parse::<u16>().is_err() {
            return Err(bad());
        }
        Ok(MetricsUrl {
            authority: authority.to_string(),
            path: path.to_string(),
        })
    }
}

/// GET `url` and return the body as text, within `timeout`.
pub async fn fetch_text(url: &str, timeout: Duration) -> Result<String, MetricsError> {
    let parsed = MetricsUrl::parse(url)?;
    let io = |source| MetricsError::Io {
        url: url.to_string(),
        source,
    };
    let exchange = async {
        let mut stream = TcpStream::connect(&parsed.authority).await.map_err(io)?;
        let request = format!(
            "GET {} HTTP/1.1\r\nHost: {}\r\nAccept: text/plain\r\nConnection: close\r\n\r\n",
            parsed.path, parsed.authority
        );
        stream.write_all(request.as_bytes()).await.map_err(io)?;
        let mut raw = Vec::new();
        (&mut stream)
            .take(MAX_RESPONSE_BYTES as u64 + 1)
            .read_to_end(&mut raw)
            .await
            .map_err(io)?;
        Ok::<_, MetricsError>(raw)
    };
    let raw = tokio::time::timeout(timeout, exchange)
        .await
        .map_err(|_| MetricsError::Timeout {
            url: url.to_string(),
            after: timeout,
        })??;
    if raw.len() > MAX_RESPONSE_BYTES {
        return Err(MetricsError::Http {
            url: url.to_string(),
            reason: format!("response larger than {MAX_RESPONSE_BYTES} bytes"),
        });
    }
    parse_response(&raw).map_err(|reason| MetricsError::Http {
        url: url.to_string(),
        reason,
    })
}

/// The body of a complete HTTP/1.x response, if its status is 200.
pub fn parse_response(raw: &[u8]) -> Result<String, String> {
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or("no end of the response headers")?;
    let head = std::str::from_utf8(&raw[..split]).map_err(|_| "headers are not UTF-8")?;
    let body = &raw[split + 4..];
    let mut lines = head.split("\r\n");
    let status = lines.next().unwrap_or_default();
    let code = status.split_whitespace().nth(1);
    if !status.starts_with("HTTP/1.") || code.is_none() {
        return Err(format!("not an HTTP/1 response: {status:?}"));
    }
    if code != Some("200") {
        return Err(format!("answered {status:?}"));
    }
    let mut chunked = false;
    let mut length = None;
    for line in lines {
        let Some((name, value)) = line.split_once(':') else {
            continue;
        };
        let value = value.trim();
        if name.eq_ignore_ascii_case("transfer-encoding") {
            chunked = value.to_ascii_lowercase().contains("chunked");
        } else if name.eq_ignore_ascii_case("content-length") {
            length = Some(
                value
                    .parse::<usize>()
                    .map_err(|_| format!("bad Content-Length {value:?}"))?,
            );
        }
    }
    let body = if chunked {
        dechunk(body)?
    } else if let Some(n) = length {
        body.get(..n)
            .ok_or_else(|| format!("body has {} of {n} bytes", body.len()))?
            .to_vec()
    } else {
        body.to_vec()
    };
    String::from_utf8(body).map_err(|_| "body is not UTF-8".into())
}

/// Decode a `Transfer-Encoding: chunked` body.
fn dechunk(mut body: &[u8]) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(body.len());
    loop {
        let eol = body
            .windows(2)
            .position(|w| w == b"\r\n")
            .ok_or("truncated chunk header")?;
        let header = std::str::from_utf8(&body[..eol]).map_err(|_| "bad chunk header")?;
        let size_hex = header.split(';').next().unwrap_or_default().trim();
        let size = usize::from_str_radix(size_hex, 16)
            .map_err(|_| format!("bad chunk size {size_hex:?}"))?;
        body = &body[eol + 2..];
        if size == 0 {
            return Ok(out);
        }
        let chunk = body.get(..size).ok_or("truncated chunk")?;
        out.extend_from_slice(chunk);
        body = body.get(size + 2..).ok_or("truncated chunk")?;
    }
}

/// One sample line: series name, labels, value.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample<'a> {
    /// Series name (e.g. `blapose_batch_size_bucket`).
    pub name: &'a str,
    /// Labels in the order given.
    pub labels: Vec<(&'a str, String)>,
    /// The value (`+Inf`, `-Inf` and `NaN` included).
    pub value: f64,
}

impl Sample<'_> {
    /// The value of label `name`.
    pub fn label(&self, name: &str) -> Option<&str> {
        self.labels
            .iter()
            .find(|(k, _)| *k == name)
            .map(|(_, v)| v.as_str())
    }
}

/// Parse one line of the text format; `None` for comments, blank lines
/// and lines that do not parse.
pub fn parse_line(line: &str) -> Option<Sample<'_>> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return None;
    }
    let name_end = line.find(|c: char| c == '{' || c.is_whitespace())?;
    let name = &line[..name_end];
    let mut rest = &line[name_end..];
    let mut labels = Vec::new();
    if let Some(inner) = rest.strip_prefix('{') {
        let (parsed, after) = parse_labels(inner)?;
        labels = parsed;
        rest = after;
    }
    let value = parse_value(rest.split_whitespace().next()?)?;
    Some(Sample {
        name,
        labels,
        value,
    })
}

/// Labels up to the closing brace; returns them and the text after it.
fn parse_labels(mut s: &str) -> Option<(Vec<(&str, String)>, &str)> {
    let mut labels = Vec::new();
    loop {
        s = s.trim_start_matches([' ', ',']);
        if let Some(after) = s.strip_prefix('}') {
            return Some((labels, after));
        }
        let eq = s.find('=')?;
        let key = s[..eq].trim();
        s = s[eq + 1..].strip_prefix('"')?;
        let mut value = String::new();
        let mut chars = s.char_indices();
        let end = loop {
            match chars.next()? {
                (i, '"') => break i,
                (_, '\\') => match chars.next()?.1 {
                    'n' => value.push('\n'),
                    c => value.push(c),
                },
                (_, c) => value.push(c),
            }
        };
        labels.push((key, value));
        s = &s[end + 1..];
    }
}

fn parse_value(s: &str) -> Option<f64> {
    match s {
        "+Inf" | "Inf" => Some(f64::INFINITY),
        "-Inf" => Some(f64::NEG_INFINITY),
        "NaN" => Some(f64::NAN),
        _ => s.parse().ok(),
    }
}

/// The value of the first sample of series `name` (any labels), e.g. a gauge.
pub fn value(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .filter_map(parse_line)
        .find(|s| s.name == name)
        .map(|s| s.value)
}

/// A Prometheus histogram without labels (other than `le`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Histogram {
    /// `(le, cumulative count)`, ascending `le`, `+Inf` last.
    pub buckets: Vec<(f64, u64)>,
    /// Sum of the observations.
    pub sum: f64,
    /// Number of observations.
    pub count: u64,
}

/// One bucket's own (non-cumulative) count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bucket {
    /// Upper bound (inclusive); infinity for the last.
    pub le: f64,
    /// Observations in `(previous le, le]`.
    pub count: u64,
}

impl Histogram {
    /// Read histogram `name` (its `_bucket`, `_sum` and `_count` series).
    /// `None` if it has no buckets (not yet recorded, or not a histogram).
    pub fn parse(text: &str, name: &str) -> Option<Histogram> {
        let bucket = format!("{name}_bucket");
        let sum = format!("{name}_sum");
        let count = format!("{name}_count");
        let mut h = Histogram::default();
        for s in text.lines().filter_map(parse_line) {
            if s.name == bucket {
                let le = parse_value(s.label("le")?)?;
                h.buckets.push((le, s.value as u64));
            } else if s.name == sum {
                h.sum = s.value;
            } else if s.name == count {
                h.count = s.value as u64;
            }
        }
        if h.buckets.is_empty() {
            return None;
        }
        h.buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
        Some(h)
    }

    /// What was observed after `earlier` (a snapshot of the same
    /// histogram taken before): counts and sum subtracted bucket by bucket.
    pub fn since(&self, earlier: Option<&Histogram>) -> Histogram {
        let Some(earlier) = earlier else {
            return self.clone();
        };
        let before = |le: f64| {
            earlier
                .buckets
                .iter()
                .find(|(l, _)| *l == le)
                .map_or(0, |(_, c)| *c)
        };
        Histogram {
            buckets: self
                .buckets
                .iter()
                .map(|&(le, c)| (le, c.saturating_sub(before(le))))
                .collect(),
            sum: (self.sum - earlier.sum).max(0.0),
            count: self.count.saturating_sub(earlier.count),
        }
    }

    /// Mean observation; `None` with no observations.
    pub fn mean(&self) -> Option<f64> {
        (self.count > 0).then(|| self.sum / self.count as f64)
    }

    /// Per-bucket counts (non-cumulative), in ascending `le`.
    pub fn bucket_counts(&self) -> Vec<Bucket> {
        let mut previous = 0;
        self.buckets
            .iter()
            .map(|&(le, cumulative)| {
                let count = cumulative.saturating_sub(previous);
                previous = previous.max(cumulative);
                Bucket { le, count }
            })
            .collect()
    }

    /// The upper bound of the bucket holding the `q`-quantile (0 < q <= 1):
    /// an upper estimate, as Prometheus buckets allow.
    pub fn quantile_upper_bound(&self, q: f64) -> Option<f64> {
        if self.count == 0 || !(q > 0.0 && q <= 1.0) {
            return None;
        }
        let rank = (q * self.count as f64).ceil() as u64;
        self.buckets
            .iter()
            .find(|(_, c)| *c >= rank)
            .map(|(le, _)| *le)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAGE: &str = r#"# HELP blapose_batch_size Frames per batched GRU step.
# TYPE blapose_batch_size histogram
blapose_batch_size_bucket{le="1"} 10
blapose_batch_size_bucket{le="2"} 12
blapose_batch_size_bucket{le="4"} 20
blapose_batch_size_bucket{le="+Inf"} 25
blapose_batch_size_sum 80
blapose_batch_size_count 25
# TYPE blapose_sessions gauge
blapose_sessions 3
blapose_errors_total{code="INVALID_ARGUMENT",rpc="Stream"} 2
blapose_frames_total{outcome="ok"} 70 1700000000000
"#;

    #[test]
    fn parses_sample_lines() {
        let s =
            parse_line(r#"blapose_errors_total{code="INVALID_ARGUMENT",rpc="Stream"} 2"#).unwrap();
        assert_eq!(s.name, "blapose_errors_total");
        assert_eq!(s.label("code"), Some("INVALID_ARGUMENT"));
        assert_eq!(s.label("rpc"), Some("Stream"));
        assert_eq!(s.value, 2.0);
        let s = parse_line(r#"x{a="q\"u,o}te",b="2"} +Inf"#).unwrap();
        assert_eq!(s.label("a"), Some("q\"u,o}te"));
        assert_eq!(s.value, f64::INFINITY);
        assert_eq!(parse_line("up 1 1700000000").unwrap().value, 1.0);
        assert!(parse_line("# TYPE up gauge").is_none());
        assert!(parse_line("").is_none());
        assert!(parse_line("garbage").is_none());
        assert!(parse_line(r#"x{a="unterminated} 1"#).is_none());
    }

    #[test]
    fn reads_gauges_and_histograms() {
        assert_eq!(value(PAGE, "blapose_sessions"), Some(3.0));
        assert_eq!(value(PAGE, "blapose_frames_total"), Some(70.0));
        assert_eq!(value(PAGE, "blapose_missing"), None);
        let h = Histogram::parse(PAGE, "blapose_batch_size").unwrap();
        assert_eq!(h.count, 25);
        assert_eq!(h.sum, 80.0);
        assert_eq!(h.mean(), Some(3.2));
        let counts: Vec<(f64, u64)> = h.bucket_counts().iter().map(|b| (b.le, b.count)).collect();
        assert_eq!(
            counts,
            vec![(1.0, 10), (2.0, 2), (4.0, 8), (f64::INFINITY, 5)]
        );
        assert_eq!(h.quantile_upper_bound(0.5), Some(4.0));
        assert_eq!(h.quantile_upper_bound(0.4), Some(1.0));
        assert_eq!(h.quantile_upper_bound(1.0), Some(f64::INFINITY));
        assert!(Histogram::parse(PAGE, "blapose_sessions").is_none());
    }

    #[test]
    fn histogram_delta_subtracts_the_earlier_snapshot() {
        let before = Histogram {
            buckets: vec![(1.0, 4), (2.0, 4), (f64::INFINITY, 5)],
            sum: 6.0,
            count: 5,
        };
        let after = Histogram {
            buckets: vec![(1.0, 4), (2.0, 10), (f64::INFINITY, 11)],
            sum: 22.0,
            count: 11,
        };
        let d = after.since(Some(&before));
        assert_eq!(d.buckets, vec![(1.0, 0), (2.0, 6), (f64::INFINITY, 6)]);
        assert_eq!(d.count, 6);
        assert_eq!(d.mean(), Some(16.0 / 6.0));
        assert_eq!(after.since(None), after);
        assert_eq!(Histogram::default().mean(), None);
    }

    #[test]
    fn urls() {
        let u = MetricsUrl::parse("http://127.0.0.1:9090").unwrap();
        assert_eq!(u.authority, "127.0.0.1:9090");
        assert_eq!(u.path, "/metrics");
        let u = MetricsUrl::parse("http://[::1]:9090/m?x=1").unwrap();
        assert_eq!(u.authority, "[::1]:9090");
        assert_eq!(u.path, "/m?x=1");
        for bad in [
            "https://a:1",
            "127.0.0.1:9090",
            "http://host",
            "http://:80",
            "http://a:x/",
        ] {
            assert!(MetricsUrl::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn http_responses() {
        let plain = b"HTTP/1.1 200 OK\r\ncontent-length: 5\r\n\r\nhello";
        assert_eq!(parse_response(plain).unwrap(), "hello");
        let chunked =
            b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n7;x=y\r\n, world\r\n0\r\n\r\n";
        assert_eq!(parse_response(chunked).unwrap(), "hello, world");
        let close_delimited = b"HTTP/1.0 200 OK\r\n\r\nall of it";
        assert_eq!(parse_response(close_delimited).unwrap(), "all of it");
        assert!(parse_response(b"HTTP/1.1 404 Not Found\r\n\r\n")
            .unwrap_err()
            .contains("404"));
        assert!(parse_response(b"HTTP/1.1 200 OK\r\ncontent-length: 9\r\n\r\nshort").is_err());
        assert!(
            parse_response(b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhe")
                .is_err()
        );
        assert!(parse_response(b"SSH-2.0\r\n\r\n").is_err());
        assert!(parse_response(b"HTTP/1.1 200 OK\r\n").is_err());
    }

    #[tokio::test]
    async fn fetch_reports_the_url_when_nothing_listens() {
        // Bind and drop: the port is (almost certainly) closed now.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let url = format!("http://127.0.0.1:{port}/metrics");
        let err = fetch_text(&url, Duration::from_secs(5)).await.unwrap_err();
        assert!(err.to_string().contains(&url), "{err}");
    }

    #[tokio::test]
    async fn fetch_reads_a_page_from_a_tiny_server() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let server = tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.unwrap();
            let mut buf = vec![0; 1024];
            let n = s.read(&mut buf).await.unwrap();
            let request = String::from_utf8_lossy(&buf[..n]).to_string();
            s.write_all(b"HTTP/1.1 200 OK\r\ncontent-length: 12\r\n\r\nblapose_up 1")
                .await
                .unwrap();
            request
        });
        let text = fetch_text(&format!("http://{addr}/metrics"), Duration::from_secs(5))
            .await
            .unwrap();
        assert_eq!(value(&text, "blapose_up"), Some(1.0));
        let request = server.await.unwrap();
        assert!(
            request.starts_with("GET /metrics HTTP/1.1\r\n"),
            "{request}"
        );
        assert!(request.contains(&format!("Host: {addr}\r\n")));
    }
}
