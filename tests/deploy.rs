//! The deployment files under `examples/deploy/` (Dockerfile, docker compose, Kubernetes
//! manifests) are parsed and checked against the real binary: every `nephele` command and
//! flag they use exists (`nephele <command> --help`), every port a process listens on is
//! the one its container, compose service or Kubernetes Service publishes, every address a
//! process dials names something that listens there, every Secret and scale target they
//! refer to exists, and the heavy farm asks for GPUs. No container is started: there is no
//! registry or Docker engine here.

use std::collections::{BTreeMap, BTreeSet};

use nephele_e2e::{nephele, repo};
use yaml_rust2::{Yaml, YamlLoader};

/// `nephele <command> --help` for each command, once.
struct Help(BTreeMap<String, String>);

impl Help {
    fn new() -> Self {
        Self(BTreeMap::new())
    }

    /// Checks that `args` (a command line after `nephele`) is a real command with real flags.
    fn check(&mut self, args: &[String], place: &str) {
        let command = args.first().unwrap_or_else(|| panic!("{place}: an empty nephele command"));
        let help = self.0.entry(command.clone()).or_insert_with(|| {
            let out = nephele().args([command.as_str(), "--help"]).output().unwrap();
            assert!(out.status.success(), "{place}: `nephele {command}` is not a command: {}", String::from_utf8_lossy(&out.stderr));
            String::from_utf8_lossy(&out.stdout).into_owned()
        });
        for flag in args.iter().filter(|a| a.starts_with("--")) {
            let flag = flag.split('=').next().unwrap();
            assert!(help.contains(&format!("{flag} ")) || help.contains(&format!("{flag}\n")), "{place}: `nephele {command}` has no {flag}");
        }
    }
}

fn strings(y: &Yaml) -> Vec<String> {
    y.as_vec().map(|v| v.iter().filter_map(|s| s.as_str().map(str::to_owned).or_else(|| s.as_i64().map(|i| i.to_string()))).collect()).unwrap_or_default()
}

/// The value after `flag` in `args`.
fn flag_value<'a>(args: &'a [String], flag: &str) -> Option<&'a str> {
    args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).map(String::as_str)
}

fn port_of(addr: &str) -> u16 {
    addr.rsplit(':').next().unwrap().split('/').next().unwrap().parse().unwrap_or_else(|_| panic!("no port in {addr}"))
}

/// (host, port) of a URL like nats://host:4222 or ws://host:8000/signal.
fn host_port(url: &str) -> (String, u16) {
    let rest = url.split("://").nth(1).unwrap_or_else(|| panic!("not a URL: {url}"));
    let hostport = rest.split('/').next().unwrap();
    let (host, port) = hostport.rsplit_once(':').unwrap_or_else(|| panic!("no port in {url}"));
    (host.to_owned(), port.parse().unwrap())
}

#[test]
fn dockerfile_runs_the_binary_and_exposes_its_ports() {
    let text = std::fs::read_to_string(repo().join("examples/deploy/Dockerfile")).unwrap();
    assert!(text.contains("ENTRYPOINT [\"nephele\"]"), "the image's entry point is nephele");
    let exposed: BTreeSet<u16> = text.lines().filter_map(|l| l.strip_prefix("EXPOSE ")).flat_map(|l| l.split_whitespace().map(|p| p.parse::<u16>().unwrap())).collect();
    let cmd = text.lines().find_map(|l| l.strip_prefix("CMD ")).expect("a CMD");
    let args: Vec<String> = serde_json::from_str(cmd).unwrap();
    Help::new().check(&args, "Dockerfile CMD");
    assert!(exposed.contains(&port_of(flag_value(&args, "--listen").unwrap())));
    assert!(exposed.is_superset(&[8000, 8080, 9100].into()), "{exposed:?}");
    assert!(text.contains("COPY --from=build /src/target/release/nephele"), "the release binary goes into the image");
    let build = text.lines().find(|l| l.starts_with("RUN cargo build")).expect("a cargo build step");
    assert!(build.contains("--locked") && build.contains("--no-default-features"), "the image builds from the lock file, without training: {build}");
    assert!(text.contains(" nasm"), "the builder has nasm for OpenH264's assembly");
}

#[test]
fn compose_services_use_real_commands_flags_and_ports() {
    let text = std::fs::read_to_string(repo().join("examples/deploy/compose.yaml")).unwrap();
    let doc = &YamlLoader::load_from_str(&text).unwrap()[0];
    let services = doc["services"].as_hash().expect("services");
    let mut help = Help::new();
    // What each service listens on, and what it publishes on the host.
    let mut listens: BTreeMap<String, BTreeSet<u16>> = BTreeMap::new();
    let mut published: BTreeSet<u16> = BTreeSet::new();
    let mut dials: Vec<(String, String)> = Vec::new();
    for (name, svc) in services {
        let name = name.as_str().unwrap().to_owned();
        for p in strings(&svc["ports"]) {
            let (host, container) = p.split_once(':').unwrap();
            assert_eq!(host, container, "{name}: publish ports unchanged ({p})");
            published.insert(host.parse().unwrap());
        }
        let command = strings(&svc["command"]);
        let ours = svc["image"].as_str() == Some("nephele");
        if ours {
            help.check(&command, &format!("compose service {name}"));
            for flag in ["--listen", "--metrics-listen"] {
                if let Some(addr) = flag_value(&command, flag) {
                    let port = port_of(addr);
                    listens.entry(name.clone()).or_default().insert(port);
                    let host_net = svc["network_mode"].as_str() == Some("host");
                    assert!(host_net || strings(&svc["ports"]).iter().any(|p| p.ends_with(&format!(":{port}"))) || flag == "--metrics-listen", "{name} listens on {port} but does not publish it");
                }
            }
            for flag in ["--nats", "--signal"] {
                if let Some(url) = flag_value(&command, flag) {
                    dials.push((name.clone(), url.to_owned()));
                }
            }
            if flag_value(&command, "--nats").is_some() {
                assert!(svc["environment"]["NEPHELE_NATS_TOKEN"].as_str().is_some(), "{name} needs the NATS token");
            }
        } else if let Some(port) = flag_value(&command, "--port") {
            listens.entry(name.clone()).or_default().insert(port.parse().unwrap());
            assert!(command.iter().any(|a| a == "--auth"), "{name}: NATS without auth");
        }
    }
    for (from, url) in dials {
        let (host, port) = host_port(&url);
        let reachable = if host == "127.0.0.1" || host == "localhost" { published.contains(&port) } else { listens.get(&host).is_some_and(|p| p.contains(&port)) };
        assert!(reachable, "{from} dials {url}, but nothing listens there");
    }
    let heavy = &services[&Yaml::String("worker-heavy".into())];
    assert!(strings(&heavy["command"]).windows(2).any(|w| w == ["--farm", "heavy"]));
    assert_eq!(heavy["deploy"]["resources"]["reservations"]["devices"][0]["capabilities"][0].as_str(), Some("gpu"));
}

#[test]
fn kubernetes_manifests_use_real_commands_flags_ports_and_names() {
    let dir = repo().join("examples/deploy/k8s");
    let mut docs = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "yaml") {
            docs.extend(YamlLoader::load_from_str(&std::fs::read_to_string(&path).unwrap()).unwrap_or_else(|e| panic!("{}: {e}", path.display())));
        }
    }
    let kind = |d: &Yaml| d["kind"].as_str().unwrap_or_default().to_owned();
    let name = |d: &Yaml| d["metadata"]["name"].as_str().unwrap_or_default().to_owned();
    let secrets: BTreeSet<String> = docs.iter().filter(|d| kind(d) == "Secret").map(|d| name(d)).collect();
    let deployments: BTreeMap<String, &Yaml> = docs.iter().filter(|d| kind(d) == "Deployment").map(|d| (name(d), d)).collect();
    let services: BTreeMap<String, &Yaml> = docs.iter().filter(|d| kind(d) == "Service").map(|d| (name(d), d)).collect();
    assert!(["nats", "signaling", "master", "worker-heavy", "worker-light"].iter().all(|d| deployments.contains_key(*d)), "{:?}", deployments.keys());
    let mut help = Help::new();
    let mut dials = Vec::new();
    // Container ports per Deployment, found by the labels a Service selects.
    let container_ports = |d: &Yaml| -> BTreeSet<u16> {
        d["spec"]["template"]["spec"]["containers"].as_vec().unwrap().iter().flat_map(|c| c["ports"].as_vec().cloned().unwrap_or_default()).filter_map(|p| p["containerPort"].as_i64()).map(|p| p as u16).collect()
    };
    for (dname, d) in &deployments {
        let pod = &d["spec"]["template"]["spec"];
        // The selector matches the pod's labels.
        let labels = d["spec"]["template"]["metadata"]["labels"].as_hash().unwrap();
        for (k, v) in d["spec"]["selector"]["matchLabels"].as_hash().unwrap() {
            assert_eq!(labels.get(k), Some(v), "{dname}: selector does not match the pod labels");
        }
        for c in pod["containers"].as_vec().unwrap() {
            for env in c["env"].as_vec().cloned().unwrap_or_default() {
                if let Some(secret) = env["valueFrom"]["secretKeyRef"]["name"].as_str() {
                    assert!(secrets.contains(secret), "{dname} reads Secret {secret}, which is not defined");
                }
            }
            if !c["image"].as_str().unwrap_or_default().starts_with("nephele") {
                continue;
            }
            let args = strings(&c["args"]);
            help.check(&args, &format!("Deployment {dname}"));
            for flag in ["--listen", "--metrics-listen"] {
                if let Some(addr) = flag_value(&args, flag) {
                    assert!(container_ports(d).contains(&port_of(addr)), "{dname} listens on {addr} but declares no such containerPort");
                }
            }
            for flag in ["--nats", "--signal"] {
                if let Some(url) = flag_value(&args, flag) {
                    dials.push((dname.clone(), url.to_owned()));
                }
            }
            if flag_value(&args, "--nats").is_some() {
                assert!(c["env"].as_vec().unwrap().iter().any(|e| e["name"].as_str() == Some("NEPHELE_NATS_TOKEN")), "{dname} needs NEPHELE_NATS_TOKEN");
            }
            if args.windows(2).any(|w| w == ["--farm", "heavy"]) {
                assert_eq!(c["resources"]["limits"]["nvidia.com/gpu"].as_i64(), Some(1), "{dname}: heavy workers request a GPU");
            }
        }
    }
    // Every Service forwards to a port its pods listen on.
    for (sname, s) in &services {
        let selector = s["spec"]["selector"].as_hash().unwrap();
        let target = deployments.values().find(|d| selector.iter().all(|(k, v)| d["spec"]["template"]["metadata"]["labels"][k.as_str().unwrap()] == *v)).unwrap_or_else(|| panic!("Service {sname} selects no Deployment"));
        for p in s["spec"]["ports"].as_vec().unwrap() {
            let target_port = p["targetPort"].as_i64().unwrap() as u16;
            assert!(container_ports(target).contains(&target_port), "Service {sname} forwards to {target_port}, which its pods do not declare");
        }
    }
    // Dialled addresses name a Service on a port it serves.
    for (from, url) in dials {
        let (host, port) = host_port(&url);
        let svc = host.split('.').next().unwrap();
        let s = services.get(svc).unwrap_or_else(|| panic!("{from} dials {url}: no Service {svc}"));
        assert!(s["spec"]["ports"].as_vec().unwrap().iter().any(|p| p["port"].as_i64() == Some(i64::from(port))), "{from} dials {url}: Service {svc} has no port {port}");
        assert!(host == svc || host.starts_with(&format!("{svc}.nephele.")), "{from} dials {url}: not in the nephele namespace");
    }
    // Autoscaling targets exist and watch the master's queue metric.
    let scalers: Vec<&Yaml> = docs.iter().filter(|d| kind(d) == "ScaledObject").collect();
    assert_eq!(scalers.len(), 2);
    for s in scalers {
        let target = s["spec"]["scaleTargetRef"]["name"].as_str().unwrap();
        assert!(deployments.contains_key(target), "ScaledObject scales {target}, which is not defined");
        let query = s["spec"]["triggers"][0]["metadata"]["query"].as_str().unwrap();
        assert!(query.contains("nephele_task_queue_depth"), "{query}");
    }
}

#[test]
fn the_metric_autoscaling_watches_exists() {
    let m = nephele_master::metrics::MasterMetrics::new().encode();
    assert!(m.contains("nephele_task_queue_depth"), "{m}");
}
