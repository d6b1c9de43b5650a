//! Which bearer token a browser's request presents. Browsers cannot set
//! headers on a WebSocket, so besides the `authorization: Bearer` header
//! the token may come as a `bearer.<token>` subprotocol offered beside
//! `blapose.v1`, or a `token` query parameter (the socket and the export
//! both read it here).

use std::collections::HashMap;

use axum::http::HeaderMap;

use crate::auth::bearer_token;

/// The subprotocol prefix that carries the bearer token.
pub const TOKEN_PROTOCOL_PREFIX: &str = "bearer.";

/// The token a request presents: the authorization header's, the
/// `bearer.` subprotocol's, or the `token` query parameter.
pub fn presented_token(headers: &HeaderMap, query: &HashMap<String, String>) -> Option<Vec<u8>> {
    if let Some(value) = headers.get(axum::http::header::AUTHORIZATION) {
        // Another scheme is a wrong token, not a missing one.
        return Some(bearer_token(value.as_bytes()).unwrap_or(b"").to_vec());
    }
    let offered = headers
        .get_all(axum::http::header::SEC_WEBSOCKET_PROTOCOL)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(str::trim)
        .find_map(|p| p.strip_prefix(TOKEN_PROTOCOL_PREFIX));
    if let Some(token) = offered {
        return Some(token.as_bytes().to_vec());
    }
    query.get("token").map(|t| t.as_bytes().to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_token_comes_from_header_subprotocol_or_query() {
        let mut headers = HeaderMap::new();
        let mut query = HashMap::new();
        assert_eq!(presented_token(&headers, &query), None);
        query.insert("token".to_string(), "q".to_string());
        assert_eq!(presented_token(&headers, &query), Some(b"q".to_vec()));
        headers.insert(
            axum::http::header::SEC_WEBSOCKET_PROTOCOL,
            "blapose.v1, bearer.p".parse().unwrap(),
        );
        assert_eq!(presented_token(&headers, &query), Some(b"p".to_vec()));
        headers.insert(
            axum::http::header::AUTHORIZATION,
            "Basic h".parse().unwrap(),
        );
        assert_eq!(presented_token(&headers, &query), Some(vec![]));
        headers.insert(
            axum::http::header::AUTHORIZATION,
            "Bearer h".parse().unwrap(),
        );
        assert_eq!(presented_token(&headers, &query), Some(b"h".to_vec()));
    }
}
