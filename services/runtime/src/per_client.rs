//! Counters kept per client inside a service's typed counters ([`PerClient`]).
use std::collections::BTreeMap;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Counters `T` of each client, in a service's counters struct with `#[serde(flatten)]`:
/// field `name` of client `i` is the status file's counter `c{i}.{name}` (the names the
/// mapper's and loop closer's per-client counters have always had). A client is in it from
/// its first counted event on.
#[derive(Debug, Clone, PartialEq)]
pub struct PerClient<T>(BTreeMap<u32, T>);

impl<T> Default for PerClient<T> {
    fn default() -> Self {
        Self(BTreeMap::new())
    }
}

impl<T: Default> PerClient<T> {
    /// Client `c`'s counters, created (zero) on first use.
    pub fn of(&mut self, c: u32) -> &mut T {
        self.0.entry(c).or_default()
    }
}

impl<T> PerClient<T> {
    /// Client `c`'s counters, if anything was counted for it.
    pub fn get(&self, c: u32) -> Option<&T> {
        self.0.get(&c)
    }

    /// The clients' counters, by client.
    pub fn iter(&self) -> impl Iterator<Item = (u32, &T)> {
        self.0.iter().map(|(c, t)| (*c, t))
    }
}

/// `c{i}.` and the rest of a per-client counter name.
fn split_client(key: &str) -> Option<(u32, &str)> {
    let rest = key.strip_prefix('c')?;
    let (i, name) = rest.split_once('.')?;
    if i.is_empty() || !i.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((i.parse().ok()?, name))
}

impl<T: Serialize> Serialize for PerClient<T> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::{Error, SerializeMap};
        let mut map = s.serialize_map(None)?;
        for (c, t) in &self.0 {
            let serde_json::Value::Object(fields) =
                serde_json::to_value(t).map_err(S::Error::custom)?
            else {
                return Err(S::Error::custom("per-client counters must be a struct"));
            };
            for (k, v) in fields {
                if !v.is_null() {
                    map.serialize_entry(&format!("c{c}.{k}"), &v)?;
                }
            }
        }
        map.end()
    }
}

impl<'de, T: DeserializeOwned> Deserialize<'de> for PerClient<T> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let all = BTreeMap::<String, serde_json::Value>::deserialize(d)?;
        let mut fields: BTreeMap<u32, serde_json::Map<String, serde_json::Value>> = BTreeMap::new();
        for (k, v) in all {
            if let Some((c, name)) = split_client(&k) {
                fields.entry(c).or_default().insert(name.to_string(), v);
            }
        }
        let clients = fields
            .into_iter()
            .map(|(c, m)| {
                let t = serde_json::from_value(serde_json::Value::Object(m))
                    .map_err(D::Error::custom)?;
                Ok((c, t))
            })
            .collect::<Result<_, D::Error>>()?;
        Ok(Self(clients))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Default, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(default)]
    struct Client {
        received: u64,
        map_id: Option<u64>,
    }

    #[derive(Debug, Default, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(default)]
    struct Counters {
        maps: u64,
        #[serde(flatten)]
        clients: PerClient<Client>,
    }

    /// Flat `c{i}.{name}` counters in the status, the typed struct back; a `None` is left
    /// out, other counters are not taken for clients'.
    #[test]
    fn per_client_counters_are_flat_in_the_status() {
        let mut c = Counters {
            maps: 2,
            ..Counters::default()
        };
        c.clients.of(0).received = 3;
        c.clients.of(12).map_id = Some(7);
        let mut s = crate::Status::new("mapper");
        s.put_counters(&c);
        let keys: Vec<&str> = s.counters.keys().map(String::as_str).collect();
        assert_eq!(
            keys,
            ["c0.received", "c12.map_id", "c12.received", "maps"],
            "{:?}",
            s.counters
        );
        s.counters.insert("cx.received".into(), 5);
        s.counters.insert("c1received".into(), 5);
        assert_eq!(s.counters_as::<Counters>(), c);
        assert_eq!(c.clients.get(1), None);
        assert_eq!(c.clients.get(12).and_then(|k| k.map_id), Some(7));
    }
}
