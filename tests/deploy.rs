//! The deployment files under `examples/deploy/` (Dockerfile, docker compose, Kubernetes
//! via kustomize) are validated offline against their schemas (the compose spec with
//! `check-jsonschema`; the Kubernetes 1.30 API with `kubernetes-validate --strict`, on what
//! `kubectl kustomize` builds) and checked against the real binary: every `nephele` command
//! and flag they use exists (`nephele <command> --help`), every port a process listens on
//! is the one its container, compose service or Service publishes, every address a process
//! dials names something that listens there, every secret is required and none is written
//! into the files, every process has health checks, limits and no root, and each farm
//! scales on its own queue. No container is started: there is no registry or Docker engine
//! here.

use std::collections::{BTreeMap, BTreeSet};

use nephele_e2e::{nephele, py_tool, repo};
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


fn read(path: &str) -> String {
    std::fs::read_to_string(repo().join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// A compose service with its `<<: *anchor` merged in (yaml-rust2 keeps merge keys as they
/// are written).
fn merged(svc: &Yaml) -> Yaml {
    let mut out = yaml_rust2::yaml::Hash::new();
    if let Some(base) = svc["<<"].as_hash() {
        out.extend(base.iter().map(|(k, v)| (k.clone(), v.clone())));
    }
    for (k, v) in svc.as_hash().expect("a service is a map") {
        if k.as_str() != Some("<<") {
            out.insert(k.clone(), v.clone());
        }
    }
    Yaml::Hash(out)
}

/// Runs a validator; returns (success, what it printed).
fn validate(mut cmd: std::process::Command) -> (bool, String) {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

fn compose_schema_check(path: &std::path::Path) -> (bool, String) {
    let mut cmd = std::process::Command::new(py_tool("check-jsonschema"));
    cmd.args(["--builtin-schema", "vendor.compose-spec"]).arg(path);
    validate(cmd)
}

fn kubernetes_schema_check(path: &std::path::Path) -> (bool, String) {
    let mut cmd = std::process::Command::new(py_tool("kubernetes-validate"));
    cmd.args(["--strict", "--kubernetes-version", KUBERNETES_VERSION, "--quiet"]).arg(path);
    validate(cmd)
}

/// The oldest Kubernetes the manifests are written for.
const KUBERNETES_VERSION: &str = "1.30.0";

/// `kubectl kustomize examples/deploy/k8s`, as `kubectl apply -k` would apply it.
fn kustomize() -> String {
    let out = std::process::Command::new("kubectl")
        .arg("kustomize")
        .arg(repo().join("examples/deploy/k8s"))
        .output()
        .expect("kubectl is missing: install `kubernetes-client` (tests/run does)");
    assert!(out.status.success(), "kubectl kustomize failed: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn dockerfile_builds_lean_runs_unprivileged_under_an_init_and_checks_health() {
    let text = read("examples/deploy/Dockerfile");
    let instruction = |name: &str| -> Vec<String> {
        text.lines().filter_map(|l| l.strip_prefix(&format!("{name} "))).map(str::to_owned).collect()
    };
    let build = text.lines().find(|l| l.starts_with("RUN cargo build")).expect("a cargo build step");
    assert!(build.contains("--locked") && build.contains("--no-default-features"), "the image builds from the lock file, without training: {build}");
    assert!(text.contains(" nasm"), "the builder has nasm for OpenH264's assembly");
    // Not root: a numeric user (Kubernetes' runAsNonRoot can check only numbers).
    let user = instruction("USER").pop().expect("a USER");
    let uid: u32 = user.split(':').next().unwrap().parse().unwrap_or_else(|_| panic!("USER {user}: give a numeric uid"));
    assert_ne!(uid, 0, "the image runs as root");
    // An init as PID 1, so SIGTERM reaches nephele's drain.
    let entry: Vec<String> = serde_json::from_str(&instruction("ENTRYPOINT").pop().expect("an ENTRYPOINT")).unwrap();
    assert_eq!(entry, ["tini", "--", "nephele"]);
    assert!(text.contains(" tini"), "tini is installed");
    let cmd: Vec<String> = serde_json::from_str(&instruction("CMD").pop().expect("a CMD")).unwrap();
    let mut help = Help::new();
    help.check(&cmd, "Dockerfile CMD");
    // The health check asks the default command's own /readyz.
    let health = instruction("HEALTHCHECK").pop().expect("a HEALTHCHECK");
    let probe: Vec<String> = serde_json::from_str(health.split(" CMD ").nth(1).expect("HEALTHCHECK … CMD [..]")).unwrap();
    assert_eq!(probe[0], "nephele", "{health}");
    help.check(&probe[1..], "HEALTHCHECK");
    let url = text.lines().find_map(|l| l.strip_prefix("ENV NEPHELE_HEALTH_URL=")).expect("ENV NEPHELE_HEALTH_URL");
    assert_eq!(host_port(url).1, port_of(flag_value(&cmd, "--listen").unwrap()), "the health check asks another port than the default command listens on");
    assert!(url.ends_with("/readyz"), "{url}");
    let exposed: BTreeSet<String> = instruction("EXPOSE").iter().flat_map(|l| l.split_whitespace().map(str::to_owned).collect::<Vec<_>>()).collect();
    assert!(exposed.contains(&port_of(flag_value(&cmd, "--listen").unwrap()).to_string()), "{exposed:?}");
    assert!(exposed.contains(&format!("{}/udp", flag_value(&cmd, "--rtc-port").expect("the default command's media on one UDP port"))), "{exposed:?}");
    assert!(["8000", "9100"].iter().all(|p| exposed.contains(*p)), "{exposed:?}");
    // The build context leaves out build output and node_modules.
    let ignore = read(".dockerignore");
    assert!(ignore.lines().any(|l| l.trim() == "target/") && ignore.contains("node_modules"), "{ignore}");
}

#[test]
fn compose_files_pass_the_compose_spec_schema() {
    for file in ["compose.yaml", "compose.turn.yaml"] {
        let path = repo().join("examples/deploy").join(file);
        let (ok, said) = compose_schema_check(&path);
        assert!(ok, "{file} does not pass the compose spec:\n{said}");
    }
    // The validator does validate: a misspelt key fails.
    let dir = nephele_e2e::TempDir::new("compose-schema");
    let bad = dir.0.join("compose.yaml");
    std::fs::write(&bad, read("examples/deploy/compose.yaml").replacen("healthcheck:", "healthchek:", 1)).unwrap();
    let (ok, said) = compose_schema_check(&bad);
    assert!(!ok && said.contains("healthchek"), "a misspelt key passed:\n{said}");
}

#[test]
fn compose_requires_every_secret_and_publishes_only_what_browsers_need() {
    let mut help = Help::new();
    let text = read("examples/deploy/compose.yaml");
    // Every ${VAR} is required (`:?` fails the start in words), but for the optional TURN set-up.
    let optional = ["ICE_SERVERS", "TURN_SECRET"];
    for file in ["compose.yaml", "compose.turn.yaml"] {
        let body = read(&format!("examples/deploy/{file}"));
        for var in body.split("${").skip(1) {
            let name: String = var.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
            let rest = &var[name.len()..];
            let required = rest.starts_with(":?");
            let allowed = required || (file == "compose.yaml" && optional.contains(&name.as_str()) && rest.starts_with(":-"));
            assert!(allowed, "{file}: ${{{name}{}…}} has a default; a secret or address must be required", rest.chars().take(2).collect::<String>());
        }
    }
    for secret in ["NATS_TOKEN", "MASTER_TOKEN", "OPERATOR_TOKEN", "PUBLIC_IP"] {
        assert!(text.contains(&format!("${{{secret}:?")), "compose.yaml does not require {secret}");
    }
    let doc = &YamlLoader::load_from_str(&text).unwrap()[0];
    let services: BTreeMap<String, Yaml> = doc["services"].as_hash().expect("services").iter().map(|(k, v)| (k.as_str().unwrap().to_owned(), merged(v))).collect();
    let mut listens: BTreeMap<String, BTreeSet<u16>> = BTreeMap::new();
    let mut published: BTreeSet<String> = BTreeSet::new();
    let mut dials: Vec<(String, String)> = Vec::new();
    for (name, svc) in &services {
        assert!(svc["restart"].as_str().is_some(), "{name}: no restart policy");
        assert!(!svc["healthcheck"]["test"].is_badvalue(), "{name}: no healthcheck");
        assert!(svc["network_mode"].as_str() != Some("host"), "{name} takes the host's network");
        for p in strings(&svc["ports"]) {
            let (host, container) = p.split_once(':').unwrap();
            assert_eq!(host, container.trim_end_matches("/udp"), "{name}: publish ports unchanged ({p})");
            published.insert(container.to_owned());
        }
        let command = strings(&svc["command"]);
        if svc["image"].as_str() != Some("nephele") {
            if let Some(port) = flag_value(&command, "--port") {
                listens.entry(name.clone()).or_default().insert(port.parse().unwrap());
                assert!(command.iter().any(|a| a == "--auth"), "{name}: NATS without auth");
            }
            continue;
        }
        help.check(&command, &format!("compose service {name}"));
        let env = &svc["environment"];
        for flag in ["--listen", "--metrics-listen"] {
            if let Some(addr) = flag_value(&command, flag) {
                listens.entry(name.clone()).or_default().insert(port_of(addr));
            }
        }
        if let Some(addr) = flag_value(&command, "--listen") {
            assert!(published.contains(&port_of(addr).to_string()), "{name} listens on {addr} for browsers but does not publish it");
        }
        // The health check asks this service's own /readyz.
        assert_eq!(strings(&svc["healthcheck"]["test"]), ["CMD", "nephele", "health"], "{name}");
        let url = env["NEPHELE_HEALTH_URL"].as_str().unwrap_or_else(|| panic!("{name}: no NEPHELE_HEALTH_URL"));
        assert!(listens[name].contains(&host_port(url).1) && url.ends_with("/readyz"), "{name}: health URL {url} is not its own /readyz");
        if let Some(port) = flag_value(&command, "--rtc-port") {
            assert!(published.contains(&format!("{port}/udp")), "{name}: media on udp {port} is not published");
            assert!(env["NEPHELE_PUBLIC_IP"].as_str().is_some(), "{name}: no public address for its ICE candidates");
        }
        if flag_value(&command, "--nats").is_some() {
            assert!(env["NEPHELE_NATS_TOKEN"].as_str().is_some(), "{name} needs the NATS token");
        }
        if ["signal", "master"].contains(&command[0].as_str()) {
            assert!(env["NEPHELE_MASTER_TOKEN"].as_str().is_some_and(|v| v.contains(":?")), "{name}: the master token must be required");
        }
        for flag in ["--nats", "--signal"] {
            if let Some(url) = flag_value(&command, flag) {
                dials.push((name.clone(), url.to_owned()));
            }
        }
    }
    // Browsers reach signaling and the master's one media port; NATS and /metrics stay inside.
    assert_eq!(published, ["50000/udp".to_owned(), "8000".to_owned()].into(), "published: {published:?}");
    for (from, url) in dials {
        let (host, port) = host_port(&url);
        assert!(listens.get(&host).is_some_and(|p| p.contains(&port)), "{from} dials {url}, but nothing listens there");
    }
    let heavy = &services["worker-heavy"];
    assert!(strings(&heavy["command"]).windows(2).any(|w| w == ["--backend", "gpu"]));
    assert_eq!(heavy["deploy"]["resources"]["reservations"]["devices"][0]["capabilities"][0].as_str(), Some("gpu"));
    assert_eq!(strings(&heavy["profiles"]), ["gpu"], "GPU workers only where asked for");
}

#[test]
fn kubernetes_manifests_pass_the_kubernetes_schemas() {
    let dir = nephele_e2e::TempDir::new("k8s-schema");
    let built = dir.0.join("k8s.yaml");
    std::fs::write(&built, kustomize()).unwrap();
    let (ok, said) = kubernetes_schema_check(&built);
    assert!(ok, "kubectl kustomize examples/deploy/k8s does not pass Kubernetes {KUBERNETES_VERSION}:\n{said}");
    for extra in ["ingress.yaml", "coturn.yaml"] {
        let (ok, said) = kubernetes_schema_check(&repo().join("examples/deploy/k8s/extras").join(extra));
        assert!(ok, "extras/{extra} does not pass Kubernetes {KUBERNETES_VERSION}:\n{said}");
    }
    // The validator does validate: a misspelt field and a port as text fail.
    let bad = dir.0.join("bad.yaml");
    std::fs::write(&bad, std::fs::read_to_string(&built).unwrap().replacen("readinessProbe", "readinesProbe", 1).replacen("containerPort: 4222", "containerPort: \"4222\"", 1)).unwrap();
    let (ok, said) = kubernetes_schema_check(&bad);
    assert!(!ok && said.contains("readinesProbe") && said.contains("'4222' is not of type 'integer'"), "bad manifests passed:\n{said}");
}

#[test]
fn kubernetes_manifests_are_safe_probed_and_consistent_with_the_binary() {
    let docs = YamlLoader::load_from_str(&kustomize()).unwrap();
    let kind = |d: &Yaml| d["kind"].as_str().unwrap_or_default().to_owned();
    let name = |d: &Yaml| d["metadata"]["name"].as_str().unwrap_or_default().to_owned();
    assert_eq!(kind(&docs[0]), "Namespace", "the namespace must come first");
    assert_eq!(docs[0]["metadata"]["labels"]["pod-security.kubernetes.io/enforce"].as_str(), Some("restricted"));
    assert!(docs.iter().skip(1).all(|d| d["metadata"]["namespace"].as_str() == Some("nephele")), "everything in the namespace nephele");
    assert!(!docs.iter().any(|d| kind(d) == "Secret"), "a Secret in the manifests would overwrite the operator's on every apply");
    let deployments: BTreeMap<String, &Yaml> = docs.iter().filter(|d| kind(d) == "Deployment").map(|d| (name(d), d)).collect();
    let services: BTreeMap<String, &Yaml> = docs.iter().filter(|d| kind(d) == "Service").map(|d| (name(d), d)).collect();
    assert_eq!(deployments.keys().collect::<Vec<_>>(), ["master", "nats", "signaling", "worker-heavy", "worker-light"]);
    let mut help = Help::new();
    let mut dials = Vec::new();
    // Keys of nephele-secrets and nephele-site that a pod cannot start without.
    let mut required: BTreeSet<(String, String)> = BTreeSet::new();
    let container_ports = |d: &Yaml| -> BTreeSet<(u16, String)> {
        d["spec"]["template"]["spec"]["containers"]
            .as_vec()
            .unwrap()
            .iter()
            .flat_map(|c| c["ports"].as_vec().cloned().unwrap_or_default())
            .map(|p| (p["containerPort"].as_i64().unwrap() as u16, p["protocol"].as_str().unwrap_or("TCP").to_owned()))
            .collect()
    };
    for (dname, d) in &deployments {
        let pod = &d["spec"]["template"]["spec"];
        let labels = d["spec"]["template"]["metadata"]["labels"].as_hash().unwrap();
        for (k, v) in d["spec"]["selector"]["matchLabels"].as_hash().unwrap() {
            assert_eq!(labels.get(k), Some(v), "{dname}: selector does not match the pod labels");
        }
        assert!(pod["hostNetwork"].is_badvalue(), "{dname} takes the host's network");
        assert_eq!(pod["securityContext"]["runAsNonRoot"].as_bool(), Some(true), "{dname}: runAsNonRoot");
        assert!(pod["securityContext"]["runAsUser"].as_i64().is_some_and(|u| u > 0), "{dname}: a non-root uid");
        for c in pod["containers"].as_vec().unwrap() {
            let ports = container_ports(d);
            for probe in ["livenessProbe", "readinessProbe"] {
                let port = c[probe]["httpGet"]["port"].as_i64().unwrap_or_else(|| panic!("{dname}: no {probe}"));
                assert!(ports.contains(&(port as u16, "TCP".into())), "{dname}: {probe} asks port {port}, which it does not declare");
            }
            assert!(c["resources"]["requests"]["cpu"].as_str().is_some() && c["resources"]["requests"]["memory"].as_str().is_some(), "{dname}: no requests");
            assert!(c["resources"]["limits"]["memory"].as_str().is_some(), "{dname}: no memory limit");
            let sc = &c["securityContext"];
            assert_eq!(sc["allowPrivilegeEscalation"].as_bool(), Some(false), "{dname}");
            assert_eq!(strings(&sc["capabilities"]["drop"]), ["ALL"], "{dname}");
            for env in c["env"].as_vec().cloned().unwrap_or_default() {
                for (source, object) in [("secretKeyRef", "nephele-secrets"), ("configMapKeyRef", "nephele-site")] {
                    let r = &env["valueFrom"][source];
                    if let Some(n) = r["name"].as_str() {
                        assert_eq!(n, object, "{dname} reads {source} {n}: one Secret and one ConfigMap hold everything");
                        if r["optional"].as_bool() != Some(true) {
                            required.insert((object.to_owned(), r["key"].as_str().unwrap().to_owned()));
                        }
                    }
                }
            }
            if c["image"].as_str() != Some("nephele") {
                continue;
            }
            let args = strings(&c["args"]);
            help.check(&args, &format!("Deployment {dname}"));
            let metrics = flag_value(&args, "--metrics-listen").unwrap_or_else(|| panic!("{dname}: no --metrics-listen for its probes and Prometheus"));
            assert_eq!(c["readinessProbe"]["httpGet"]["path"].as_str(), Some("/readyz"), "{dname}");
            assert_eq!(c["livenessProbe"]["httpGet"]["path"].as_str(), Some("/healthz"), "{dname}");
            assert_eq!(c["readinessProbe"]["httpGet"]["port"].as_i64(), Some(i64::from(port_of(metrics))), "{dname}: probes ask the metrics listener");
            for flag in ["--listen", "--metrics-listen"] {
                if let Some(addr) = flag_value(&args, flag) {
                    assert!(ports.contains(&(port_of(addr), "TCP".into())), "{dname} listens on {addr} but declares no such containerPort");
                }
            }
            if let Some(port) = flag_value(&args, "--rtc-port") {
                let port: u16 = port.parse().expect("one media port");
                assert!(ports.contains(&(port, "UDP".into())), "{dname}: media port {port}/UDP not declared");
                let svc = services.values().find(|s| s["spec"]["ports"].as_vec().unwrap().iter().any(|p| p["protocol"].as_str() == Some("UDP"))).expect("a UDP Service for the media");
                let p = &svc["spec"]["ports"][0];
                assert_eq!((p["port"].as_i64(), p["targetPort"].as_i64(), p["nodePort"].as_i64()), (Some(port.into()), Some(port.into()), Some(port.into())), "the media port must be the same outside as inside (ICE advertises it)");
                assert_eq!(svc["spec"]["externalTrafficPolicy"].as_str(), Some("Local"), "browsers' source addresses must reach the master");
                assert!(c["env"].as_vec().unwrap().iter().any(|e| e["name"].as_str() == Some("NEPHELE_PUBLIC_IP")), "{dname}: no public address for its candidates");
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
                assert!(args.windows(2).any(|w| w == ["--backend", "gpu"]) && !args.contains(&"--allow-software-gpu".to_owned()), "{dname}: a heavy worker refuses a software adapter");
            }
        }
    }
    // Every Service forwards to a port its pods declare.
    for (sname, s) in &services {
        let selector = s["spec"]["selector"].as_hash().unwrap();
        let target = deployments.values().find(|d| selector.iter().all(|(k, v)| d["spec"]["template"]["metadata"]["labels"][k.as_str().unwrap()] == *v)).unwrap_or_else(|| panic!("Service {sname} selects no Deployment"));
        for p in s["spec"]["ports"].as_vec().unwrap() {
            let target_port = p["targetPort"].as_i64().unwrap() as u16;
            assert!(container_ports(target).contains(&(target_port, p["protocol"].as_str().unwrap_or("TCP").to_owned())), "Service {sname} forwards to {target_port}, which its pods do not declare");
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
    // NATS admits only masters and workers.
    let policy = docs.iter().find(|d| kind(d) == "NetworkPolicy").expect("a NetworkPolicy for NATS");
    assert_eq!(policy["spec"]["podSelector"]["matchLabels"]["app"].as_str(), Some("nats"));
    // The operator's commands in docs/deployment.md create every key a pod needs.
    let guide = read("docs/deployment.md");
    for (object, key) in &required {
        let command = if object == "nephele-secrets" { "create secret generic nephele-secrets" } else { "create configmap nephele-site" };
        let at = guide.find(command).unwrap_or_else(|| panic!("docs/deployment.md never says `kubectl … {command}`"));
        let block = &guide[at..guide[at..].find("\n\n").map_or(guide.len(), |e| at + e)];
        assert!(block.contains(&format!("--from-literal={key}=")), "docs/deployment.md's `{command}` lacks {key}:\n{block}");
    }
    assert!(required.contains(&("nephele-secrets".into(), "master-token".into())) && required.contains(&("nephele-site".into(), "public-ip".into())), "{required:?}");
}

#[test]
fn each_farm_scales_on_its_own_queue() {
    let docs = YamlLoader::load_from_str(&read("examples/deploy/k8s/extras/keda.yaml")).unwrap();
    let built = YamlLoader::load_from_str(&kustomize()).unwrap();
    assert_eq!(docs.len(), 2);
    for s in &docs {
        assert_eq!(s["kind"].as_str(), Some("ScaledObject"));
        let target = s["spec"]["scaleTargetRef"]["name"].as_str().unwrap();
        let deployment = built.iter().find(|d| d["kind"].as_str() == Some("Deployment") && d["metadata"]["name"].as_str() == Some(target)).unwrap_or_else(|| panic!("ScaledObject scales {target}, which is not defined"));
        let args = strings(&deployment["spec"]["template"]["spec"]["containers"][0]["args"]);
        let farm = flag_value(&args, "--farm").unwrap();
        let query = s["spec"]["triggers"][0]["metadata"]["query"].as_str().unwrap();
        assert_eq!(query, format!("sum(nephele_task_queue_depth{{farm=\"{farm}\"}})"), "{target} must scale on its own farm's queue");
    }
    // And the master exports that series, by farm.
    let m = nephele_master::metrics::MasterMetrics::new();
    m.record(&nephele_core::events::CoreEvent::Queue { waiting_heavy: 3, waiting_light: 5, in_flight: 0, rays_in_flight: 0, farm_rays_per_s: 0.0 });
    let text = m.encode();
    assert!(text.contains("nephele_task_queue_depth{farm=\"heavy\"} 3") && text.contains("nephele_task_queue_depth{farm=\"light\"} 5"), "{text}");
}

/// A heavy worker on a machine whose only Vulkan adapter is software refuses to start, in
/// words; `--allow-software-gpu` lets it go on (to NATS, which is not there).
#[test]
fn a_gpu_worker_refuses_a_software_adapter() {
    let run = |extra: &[&str]| {
        let out = nephele()
            .args(["worker", "--nats", "nats://127.0.0.1:9", "--farm", "heavy", "--backend", "gpu", "--scene", "builtin:trio-small"])
            .args(extra)
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap();
        (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (ok, said) = run(&[]);
    assert!(!ok && said.contains("found only a software adapter") && said.contains("--allow-software-gpu"), "{said}");
    let (ok, said) = run(&["--allow-software-gpu"]);
    assert!(!ok && said.contains("cannot reach NATS"), "with --allow-software-gpu it should get as far as NATS: {said}");
}

/// Every `nephele` command line in docs/deployment.md's shell blocks (the fresh-VM guide's
/// systemd unit, the TURN example, `docker run`) uses real commands and flags.
#[test]
fn the_deployment_guide_gives_real_commands() {
    let guide = read("docs/deployment.md");
    let mut in_code = false;
    let mut lines = guide.lines().peekable();
    let mut checked = 0;
    let mut help = Help::new();
    while let Some(line) = lines.next() {
        if line.starts_with("```") {
            in_code = !in_code;
            continue;
        }
        // Where "nephele <role>" starts (after a space or the path's slash).
        let Some(at) = ["serve", "signal", "master", "worker"].iter().find_map(|role| line.find(&format!("nephele {role} ")).filter(|&i| i > 0 && matches!(&line[i - 1..i], " " | "/"))) else { continue };
        if !in_code {
            continue;
        }
        // The command with its continuation lines.
        let mut command = line[at..].to_owned();
        while command.trim_end().ends_with('\\') {
            command = format!("{} {}", command.trim_end().trim_end_matches('\\'), lines.next().unwrap_or_default());
        }
        let args: Vec<String> = command.split_whitespace().skip(1).map(|a| a.trim_matches(['"', '\'']).to_owned()).collect();
        help.check(&args, &format!("docs/deployment.md: {}", line.trim()));
        checked += 1;
    }
    assert!(checked >= 3, "found only {checked} nephele command lines in the guide");
}
