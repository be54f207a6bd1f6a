//! ICE servers: STUN and TURN as an operator names them (`--ice-server URL`) and as each
//! client receives them in `joined` (the shape of the browser's `RTCIceServer`).
//!
//! URLs follow RFC 7064 (`stun:` / `stuns:` HOST[:PORT]) and RFC 7065 (`turn:` / `turns:`
//! HOST[:PORT][?transport=udp|tcp]). TURN needs credentials, either static (one username and
//! password for everybody) or minted per session by the TURN REST scheme that coturn's
//! `use-auth-secret` implements: username `EXPIRY:ID` (EXPIRY in Unix seconds), password
//! base64(HMAC-SHA1(secret, username)). The secret stays on the server; a client gets only
//! a credential that expires.

use std::{fmt, str::FromStr};

use base64::Engine as _;
use hmac::{Hmac, Mac};
use serde::{Deserialize, Serialize};

/// One entry of a peer connection's `iceServers`, as a browser takes it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct IceServer {
    pub urls: Vec<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub username: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub credential: Option<String>,
}

/// The URL schemes of RFC 7064 and RFC 7065.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IceScheme {
    Stun,
    Stuns,
    Turn,
    Turns,
}

impl IceScheme {
    pub fn is_turn(self) -> bool {
        matches!(self, Self::Turn | Self::Turns)
    }
}

/// A checked STUN or TURN URL; [`fmt::Display`] gives it back as written.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IceUrl {
    pub scheme: IceScheme,
    pub host: String,
    /// As written, or the scheme's default (3478; 5349 for `stuns:`/`turns:`).
    pub port: u16,
    /// TURN only: the transport to the TURN server, when given.
    pub transport: Option<String>,
    text: String,
}

impl FromStr for IceUrl {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let bad = |why: &str| format!("ICE server URL {text:?}: {why} (e.g. stun:stun.example.org:3478 or turn:turn.example.org:3478?transport=udp)");
        let (scheme, rest) = text.split_once(':').ok_or_else(|| bad("no scheme"))?;
        let scheme = match scheme.to_ascii_lowercase().as_str() {
            "stun" => IceScheme::Stun,
            "stuns" => IceScheme::Stuns,
            "turn" => IceScheme::Turn,
            "turns" => IceScheme::Turns,
            other => return Err(bad(&format!("the scheme is {other:?}, not stun, stuns, turn or turns"))),
        };
        if rest.starts_with("//") {
            return Err(bad("no \"//\" after the scheme"));
        }
        if rest.contains('@') {
            return Err(bad("credentials go in --turn-username/--turn-credential or --turn-secret, not in the URL"));
        }
        let (hostport, query) = match rest.split_once('?') {
            Some((h, q)) => (h, Some(q)),
            None => (rest, None),
        };
        let transport = match query {
            None => None,
            Some(_) if !scheme.is_turn() => return Err(bad("only turn: and turns: URLs take a query")),
            Some(q) => match q.strip_prefix("transport=") {
                Some(t @ ("udp" | "tcp")) => Some(t.to_owned()),
                _ => return Err(bad("the only query is transport=udp or transport=tcp")),
            },
        };
        let (host, port) = if let Some(v6) = hostport.strip_prefix('[') {
            let (addr, after) = v6.split_once(']').ok_or_else(|| bad("an unclosed [IPv6 address]"))?;
            addr.parse::<std::net::Ipv6Addr>().map_err(|_| bad("not an IPv6 address in [ ]"))?;
            (addr.to_owned(), after.strip_prefix(':'))
        } else {
            match hostport.rsplit_once(':') {
                Some((h, p)) => (h.to_owned(), Some(p)),
                None => (hostport.to_owned(), None),
            }
        };
        let host_ok = !host.is_empty() && host.len() <= 253 && host.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | ':'));
        if !host_ok {
            return Err(bad("no host, or a host that is neither a name nor an address"));
        }
        let port = match port {
            None => match scheme {
                IceScheme::Stuns | IceScheme::Turns => 5349,
                _ => 3478,
            },
            Some(p) => p.parse::<u16>().ok().filter(|&p| p > 0).ok_or_else(|| bad("the port is not a number in 1..=65535"))?,
        };
        Ok(Self { scheme, host, port, transport, text: text.to_owned() })
    }
}

impl fmt::Display for IceUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

/// How TURN servers are logged into.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum TurnAuth {
    /// No TURN server configured.
    #[default]
    None,
    /// The same username and password for every session.
    Static { username: String, credential: String },
    /// TURN REST credentials minted per session from a secret shared with the TURN server,
    /// valid for `ttl_s` seconds.
    Secret { secret: String, ttl_s: u64 },
}

/// The ICE servers of a deployment and how to log into its TURN servers.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct IceConfig {
    pub urls: Vec<IceUrl>,
    pub turn: TurnAuth,
}

/// Longest TURN REST credential lifetime accepted (a week).
pub const MAX_TURN_TTL_S: u64 = 7 * 24 * 3600;

impl IceConfig {
    /// Checks that every TURN URL has credentials and that credentials have a TURN URL.
    pub fn new(urls: Vec<IceUrl>, turn: TurnAuth) -> Result<Self, String> {
        let has_turn = urls.iter().any(|u| u.scheme.is_turn());
        match (&turn, has_turn) {
            (TurnAuth::None, true) => return Err("a turn: or turns: ICE server needs --turn-username and --turn-credential, or --turn-secret".into()),
            (TurnAuth::Static { .. } | TurnAuth::Secret { .. }, false) => return Err("TURN credentials were given but no turn: or turns: --ice-server".into()),
            (TurnAuth::Static { username, credential }, true) if username.is_empty() || credential.is_empty() || username.contains(':') => {
                return Err("--turn-username needs --turn-credential, both non-empty, and the username without ':'".into());
            }
            (TurnAuth::Secret { secret, ttl_s }, true) if secret.is_empty() || *ttl_s == 0 || *ttl_s > MAX_TURN_TTL_S => {
                return Err(format!("--turn-secret must not be empty and --turn-ttl must be 1..={MAX_TURN_TTL_S} s"));
            }
            _ => {}
        }
        Ok(Self { urls, turn })
    }

    pub fn is_empty(&self) -> bool {
        self.urls.is_empty()
    }

    /// [`IceConfig::servers_for`] now (TURN credentials expire in wall-clock time).
    pub fn servers_now(&self, id: &str) -> Vec<IceServer> {
        let unix_now_s = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        self.servers_for(unix_now_s, id)
    }

    /// The `iceServers` for one session at `unix_now_s`: the STUN URLs as one entry, the
    /// TURN URLs as another with the session's credentials (minted for `id` when from a
    /// secret). `id` names the session in the TURN server's logs; keep personal data out.
    pub fn servers_for(&self, unix_now_s: u64, id: &str) -> Vec<IceServer> {
        let pick = |turn: bool| self.urls.iter().filter(|u| u.scheme.is_turn() == turn).map(ToString::to_string).collect::<Vec<_>>();
        let (stun, turn) = (pick(false), pick(true));
        let mut out = Vec::new();
        if !stun.is_empty() {
            out.push(IceServer { urls: stun, username: None, credential: None });
        }
        if !turn.is_empty() {
            let (username, credential) = match &self.turn {
                TurnAuth::None => return out,
                TurnAuth::Static { username, credential } => (username.clone(), credential.clone()),
                TurnAuth::Secret { secret, ttl_s } => turn_rest_credentials(secret, unix_now_s.saturating_add(*ttl_s), id),
            };
            out.push(IceServer { urls: turn, username: Some(username), credential: Some(credential) });
        }
        out
    }
}

/// TURN REST credentials valid until `expiry_unix_s`: (`EXPIRY:ID`, base64(HMAC-SHA1)).
pub fn turn_rest_credentials(secret: &str, expiry_unix_s: u64, id: &str) -> (String, String) {
    let username = format!("{expiry_unix_s}:{id}");
    let mut mac = Hmac::<sha1::Sha1>::new_from_slice(secret.as_bytes()).expect("HMAC takes a key of any length");
    mac.update(username.as_bytes());
    let password = base64::engine::general_purpose::STANDARD.encode(mac.finalize().into_bytes());
    (username, password)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_parse_with_default_ports_and_transports() {
        let u: IceUrl = "stun:stun.example.org".parse().unwrap();
        assert_eq!((u.scheme, u.host.as_str(), u.port, u.transport.as_deref()), (IceScheme::Stun, "stun.example.org", 3478, None));
        let u: IceUrl = "turns:turn.example.org?transport=tcp".parse().unwrap();
        assert_eq!((u.scheme, u.port, u.transport.as_deref()), (IceScheme::Turns, 5349, Some("tcp")));
        let u: IceUrl = "turn:[::1]:3479?transport=udp".parse().unwrap();
        assert_eq!((u.host.as_str(), u.port), ("::1", 3479));
        let u: IceUrl = "TURN:10.0.0.1:443".parse().unwrap();
        assert_eq!((u.scheme, u.port, u.to_string()), (IceScheme::Turn, 443, "TURN:10.0.0.1:443".to_string()));
    }

    #[test]
    fn malformed_urls_are_refused_in_words() {
        for (text, says) in [
            ("turn.example.org", "no scheme"),
            ("http://turn.example.org", "not stun"),
            ("stun://stun.example.org", "no \"//\""),
            ("turn:user:pw@turn.example.org", "credentials go in"),
            ("stun:stun.example.org?transport=udp", "only turn:"),
            ("turn:turn.example.org?transport=sctp", "transport=udp"),
            ("turn:turn.example.org:0", "port"),
            ("turn:turn.example.org:99999", "port"),
            ("stun:", "no host"),
            ("stun:bad host", "no host"),
            ("turn:[::1:3478", "unclosed"),
            ("turn:[nope]:3478", "IPv6"),
        ] {
            let err = text.parse::<IceUrl>().unwrap_err();
            assert!(err.contains(says), "{text}: {err}");
        }
    }

    #[test]
    fn turn_needs_credentials_and_credentials_need_turn() {
        let turn: IceUrl = "turn:t.example.org".parse().unwrap();
        let stun: IceUrl = "stun:s.example.org".parse().unwrap();
        assert!(IceConfig::new(vec![turn.clone()], TurnAuth::None).unwrap_err().contains("needs --turn-username"));
        assert!(IceConfig::new(vec![stun.clone()], TurnAuth::Secret { secret: "s".into(), ttl_s: 60 }).unwrap_err().contains("no turn:"));
        assert!(IceConfig::new(vec![turn.clone()], TurnAuth::Secret { secret: "s".into(), ttl_s: 0 }).is_err());
        assert!(IceConfig::new(vec![turn.clone()], TurnAuth::Static { username: "a:b".into(), credential: "c".into() }).is_err());
        assert!(IceConfig::new(vec![stun, turn], TurnAuth::Static { username: "a".into(), credential: "c".into() }).is_ok());
        assert!(IceConfig::new(vec![], TurnAuth::None).unwrap().is_empty());
    }

    /// The scheme coturn checks (`use-auth-secret`); the expected password is Python's
    /// `base64.b64encode(hmac.new(b"north-sea", b"1700000000:nephele-s7", hashlib.sha1).digest())`.
    #[test]
    fn rest_credentials_match_the_turn_rest_scheme() {
        let (user, pass) = turn_rest_credentials("north-sea", 1_700_000_000, "nephele-s7");
        assert_eq!(user, "1700000000:nephele-s7");
        assert_eq!(pass, "EwQh+miGVk8UsAn/nXktHlgdyg8=");
    }

    #[test]
    fn each_session_gets_stun_and_its_own_expiring_turn_credential() {
        let urls = ["stun:s.example.org", "turn:t.example.org?transport=udp", "turns:t.example.org:443?transport=tcp"].map(|u| u.parse().unwrap()).to_vec();
        let cfg = IceConfig::new(urls, TurnAuth::Secret { secret: "k".into(), ttl_s: 600 }).unwrap();
        let a = cfg.servers_for(1000, "nephele-s1");
        assert_eq!(a.len(), 2);
        assert_eq!(a[0], IceServer { urls: vec!["stun:s.example.org".into()], username: None, credential: None });
        assert_eq!(a[1].urls, vec!["turn:t.example.org?transport=udp".to_string(), "turns:t.example.org:443?transport=tcp".into()]);
        assert_eq!(a[1].username.as_deref(), Some("1600:nephele-s1"));
        let b = cfg.servers_for(1000, "nephele-s2");
        assert_ne!(a[1].credential, b[1].credential);
        // Serialised as a browser's RTCIceServer, without the secret.
        let json = serde_json::to_string(&a).unwrap();
        assert!(json.contains("\"urls\"") && json.contains("\"credential\"") && !json.contains("\"k\""), "{json}");
        assert_eq!(serde_json::to_string(&a[0]).unwrap(), r#"{"urls":["stun:s.example.org"]}"#);
    }
}
