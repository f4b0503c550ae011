//! `deploy/`'s manifests, checked without a cluster (none is reachable here): every
//! Kubernetes document is well formed and has the fields its kind requires, every reference
//! resolves (Services to pods, probes and targetPorts to named ports, volumes to claims,
//! envFrom to ConfigMaps, `$(VAR)`s to variables, the autoscaler to its Deployment, Service
//! and to metrics the master really exports), the kustomization lists every file; and every
//! command line in the manifests and in `deploy/docker-compose.yml` uses only flags the
//! `nephele` binary accepts.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use nephele_tests::nephele;
use serde_json::Value;
use yaml_rust2::{Yaml, YamlLoader};

fn deploy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("workspace root").join("deploy")
}

/// A YAML node as JSON (merge keys `<<` expanded; aliases are resolved by the loader).
fn to_json(yaml: &Yaml) -> Value {
    match yaml {
        Yaml::Real(r) => r.parse::<f64>().map_or_else(|_| Value::String(r.clone()), Value::from),
        Yaml::Integer(i) => Value::from(*i),
        Yaml::String(s) => Value::String(s.clone()),
        Yaml::Boolean(b) => Value::Bool(*b),
        Yaml::Array(items) => Value::Array(items.iter().map(to_json).collect()),
        Yaml::Hash(hash) => {
            let mut map = serde_json::Map::new();
            let mut merged = serde_json::Map::new();
            for (k, v) in hash {
                let key = match k {
                    Yaml::String(s) => s.clone(),
                    Yaml::Integer(i) => i.to_string(),
                    other => panic!("unsupported mapping key {other:?}"),
                };
                if key == "<<" {
                    if let Value::Object(m) = to_json(v) {
                        merged.extend(m);
                    }
                } else {
                    map.insert(key, to_json(v));
                }
            }
            for (k, v) in merged {
                map.entry(k).or_insert(v);
            }
            Value::Object(map)
        }
        Yaml::Null => Value::Null,
        Yaml::Alias(_) | Yaml::BadValue => panic!("unresolved YAML node {yaml:?}"),
    }
}

fn load(path: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let docs = YamlLoader::load_from_str(&text).unwrap_or_else(|e| panic!("{}: not YAML: {e}", path.display()));
    docs.iter().map(to_json).filter(|d| !d.is_null()).collect()
}

fn str_at<'a>(v: &'a Value, pointer: &str) -> Option<&'a str> {
    v.pointer(pointer).and_then(Value::as_str)
}

fn items<'a>(v: &'a Value, pointer: &str) -> Vec<&'a Value> {
    v.pointer(pointer).and_then(Value::as_array).map(|a| a.iter().collect()).unwrap_or_default()
}

/// `(kind, name)` → document, over every file the kustomization lists.
fn manifests() -> BTreeMap<(String, String), Value> {
    let dir = deploy_dir().join("k8s");
    let kustomization = load(&dir.join("kustomization.yaml")).remove(0);
    let listed: BTreeSet<String> =
        items(&kustomization, "/resources").iter().filter_map(|r| r.as_str().map(str::to_string)).collect();
    let on_disk: BTreeSet<String> = std::fs::read_dir(&dir)
        .expect("deploy/k8s")
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.ends_with(".yaml") && n != "kustomization.yaml")
        .collect();
    assert_eq!(listed, on_disk, "kustomization.yaml must list exactly the manifests in deploy/k8s");
    let mut all = BTreeMap::new();
    for file in &listed {
        for doc in load(&dir.join(file)) {
            let kind = str_at(&doc, "/kind").unwrap_or_else(|| panic!("{file}: a document without kind"));
            assert!(str_at(&doc, "/apiVersion").is_some(), "{file}: {kind} without apiVersion");
            let name = str_at(&doc, "/metadata/name").unwrap_or_else(|| panic!("{file}: {kind} without a name"));
            let previous = all.insert((kind.to_string(), name.to_string()), doc.clone());
            assert!(previous.is_none(), "{file}: {kind}/{name} defined twice");
        }
    }
    all
}

fn labels_match(selector: &Value, labels: &Value) -> bool {
    selector.as_object().is_some_and(|s| !s.is_empty() && s.iter().all(|(k, v)| labels.get(k) == Some(v)))
}

/// The pod template of a workload.
fn pod_template(doc: &Value) -> Option<&Value> {
    doc.pointer("/spec/template")
}

#[test]
fn kubernetes_manifests_are_complete_and_every_reference_resolves() {
    let all = manifests();
    let named = |kind: &str, name: &str| all.contains_key(&(kind.to_string(), name.to_string()));
    let config: BTreeMap<String, String> = all
        .iter()
        .filter(|((kind, _), _)| kind == "ConfigMap")
        .flat_map(|(_, doc)| doc["data"].as_object().cloned().unwrap_or_default())
        .map(|(k, v)| (k, v.as_str().unwrap_or_default().to_string()))
        .collect();
    let mut workloads = 0;
    for ((kind, name), doc) in &all {
        let Some(template) = pod_template(doc) else { continue };
        workloads += 1;
        let what = format!("{kind}/{name}");
        if kind == "Deployment" {
            let selector = doc.pointer("/spec/selector/matchLabels").unwrap_or(&Value::Null);
            assert!(
                labels_match(selector, &template["metadata"]["labels"]),
                "{what}: selector does not match its pods"
            );
        }
        let volumes: BTreeSet<&str> =
            items(template, "/spec/volumes").iter().filter_map(|v| str_at(v, "/name")).collect();
        for volume in items(template, "/spec/volumes") {
            if let Some(claim) = str_at(volume, "/persistentVolumeClaim/claimName") {
                assert!(named("PersistentVolumeClaim", claim), "{what}: claim {claim} is not defined");
            }
        }
        let security = &template["spec"]["securityContext"];
        assert_eq!(security["runAsNonRoot"], true, "{what}: pods must run as non-root");
        for container in items(template, "/spec/containers") {
            let cname = str_at(container, "/name").unwrap_or("?");
            let what = format!("{what} container {cname}");
            assert!(str_at(container, "/image").is_some_and(|i| i.starts_with("nephele")), "{what}: image");
            for field in ["/resources/requests/cpu", "/resources/requests/memory", "/resources/limits/memory"] {
                assert!(container.pointer(field).is_some(), "{what}: {field} missing");
            }
            let ports: BTreeSet<&str> = items(container, "/ports").iter().filter_map(|p| str_at(p, "/name")).collect();
            if kind == "Deployment" {
                for probe in ["livenessProbe", "readinessProbe"] {
                    let path = str_at(container, &format!("/{probe}/httpGet/path"));
                    assert!(path.is_some(), "{what}: {probe} missing");
                    let port = str_at(container, &format!("/{probe}/httpGet/port"));
                    assert!(
                        port.is_some_and(|p| ports.contains(p)),
                        "{what}: {probe} port {port:?} is not a named port"
                    );
                    let expected = if probe == "livenessProbe" { "/livez" } else { "/readyz" };
                    assert_eq!(path, Some(expected), "{what}: {probe} path");
                }
            }
            for mount in items(container, "/volumeMounts") {
                let m = str_at(mount, "/name").unwrap_or("?");
                assert!(volumes.contains(m), "{what}: mounts undefined volume {m}");
            }
            let mut vars: BTreeSet<String> =
                items(container, "/env").iter().filter_map(|e| str_at(e, "/name").map(str::to_string)).collect();
            for source in items(container, "/envFrom") {
                let map = str_at(source, "/configMapRef/name").expect("envFrom names a ConfigMap");
                assert!(named("ConfigMap", map), "{what}: ConfigMap {map} is not defined");
                vars.extend(
                    all[&("ConfigMap".to_string(), map.to_string())]["data"]
                        .as_object()
                        .into_iter()
                        .flatten()
                        .map(|(k, _)| k.clone()),
                );
            }
            let args: Vec<&str> = items(container, "/args").iter().filter_map(|a| a.as_str()).collect();
            for arg in &args {
                for var in arg.split("$(").skip(1).filter_map(|rest| rest.split_once(')').map(|(v, _)| v)) {
                    assert!(vars.contains(var), "{what}: $({var}) is not defined");
                }
            }
            check_flags(&what, &args);
        }
    }
    assert!(workloads >= 5, "master, composer, two worker variants and the bake job");

    // Services select pods of some workload, on ports those pods name.
    for ((kind, name), doc) in all.iter().filter(|((kind, _), _)| kind == "Service") {
        let selector = doc.pointer("/spec/selector").unwrap_or(&Value::Null);
        let pods: Vec<&Value> = all
            .values()
            .filter_map(pod_template)
            .filter(|t| labels_match(selector, &t["metadata"]["labels"]))
            .collect();
        assert!(!pods.is_empty(), "{kind}/{name} selects no pods");
        for port in items(doc, "/spec/ports") {
            let target = str_at(port, "/targetPort").expect("named targetPort");
            let found = pods.iter().any(|t| {
                items(t, "/spec/containers")
                    .iter()
                    .any(|c| items(c, "/ports").iter().any(|p| str_at(p, "/name") == Some(target)))
            });
            assert!(found, "{kind}/{name}: targetPort {target} is no pod's port");
        }
    }
    // Addresses in the ConfigMap name a Service and one of its ports.
    for (key, value) in &config {
        let Some((host, port)) = value.split_once(':') else { continue };
        let Ok(port) = port.parse::<i64>() else { continue };
        let service = all.get(&("Service".to_string(), host.to_string()));
        let service = service.unwrap_or_else(|| panic!("ConfigMap {key}={value}: no Service {host}"));
        assert!(
            items(service, "/spec/ports").iter().any(|p| p["port"] == port),
            "{key}={value}: the Service has no port {port}"
        );
    }
    // Every farm process reads the farm secret and the operators' token from the Secret the
    // operator creates (deploy/README.md: its keys `farm` and `operator`), mounted where
    // NEPHELE_FARM_SECRET_FILE and NEPHELE_OPERATOR_TOKEN_FILE point.
    assert_eq!(config.get("NEPHELE_FARM_SECRET_FILE").map(String::as_str), Some("/var/lib/nephele/secrets/farm"));
    assert_eq!(
        config.get("NEPHELE_OPERATOR_TOKEN_FILE").map(String::as_str),
        Some("/var/lib/nephele/secrets/operator")
    );
    let readme = std::fs::read_to_string(deploy_dir().join("README.md")).expect("deploy/README.md");
    let creates_secret = readme
        .lines()
        .find(|l| l.contains("kubectl -n nephele create secret generic nephele-secrets"))
        .expect("deploy/README.md says how to create the Secret nephele-secrets");
    // Farm TLS: the folder is the Secret's mount, holding farm.crt and farm.key.
    assert_eq!(config.get("NEPHELE_FARM_TLS_DIR").map(String::as_str), Some("/var/lib/nephele/secrets"));
    for key in ["--from-file=farm=", "--from-file=operator=", "--from-file=farm.crt=", "--from-file=farm.key="] {
        assert!(creates_secret.contains(key), "the Secret's creation in deploy/README.md lacks {key}");
    }
    for name in ["nephele-master", "nephele-composer", "nephele-worker-cpu", "nephele-worker-gpu"] {
        let spec = &all[&("Deployment".to_string(), name.to_string())]["spec"]["template"]["spec"];
        let volume = items(spec, "/volumes")
            .into_iter()
            .find(|v| str_at(v, "/secret/secretName") == Some("nephele-secrets"))
            .unwrap_or_else(|| panic!("{name}: no volume of the Secret nephele-secrets"));
        let volume = str_at(volume, "/name").expect("volume name");
        let mounted = items(spec, "/containers/0/volumeMounts")
            .iter()
            .any(|m| str_at(m, "/name") == Some(volume) && str_at(m, "/mountPath") == Some("/var/lib/nephele/secrets"));
        assert!(mounted, "{name}: the Secret is not mounted at /var/lib/nephele/secrets");
        assert_eq!(spec["securityContext"]["fsGroup"], 10001, "{name}: the unprivileged user's group reads it");
    }
    // Every /metrics asks for that token, so the Prometheus scrape jobs given for the
    // autoscaler's metrics send it: the master's Service and the annotated pods.
    let scrape = &all[&("ConfigMap".to_string(), "nephele-prometheus-scrape".to_string())];
    let jobs = YamlLoader::load_from_str(str_at(scrape, "/data/scrape.yaml").expect("scrape.yaml")).expect("YAML");
    let jobs = to_json(&jobs[0]);
    let jobs = jobs.as_array().expect("a list of scrape jobs");
    let roles: BTreeSet<&str> = jobs.iter().filter_map(|j| str_at(j, "/kubernetes_sd_configs/0/role")).collect();
    assert_eq!(roles, BTreeSet::from(["endpoints", "pod"]), "scrape the master's Service and the annotated pods");
    for job in jobs {
        assert_eq!(str_at(job, "/authorization/type"), Some("Bearer"), "{job}");
        let file = str_at(job, "/authorization/credentials_file").unwrap_or_default();
        assert!(file.ends_with("/nephele-secrets/operator"), "{job}: the scrape sends the operators' token");
    }
    let annotated = all
        .values()
        .filter_map(pod_template)
        .filter(|t| t.pointer("/metadata/annotations/prometheus.io~1scrape").and_then(Value::as_str) == Some("true"));
    assert!(annotated.count() >= 3, "the composer and both worker variants are scraped through their annotations");
    // The GPU variant asks for a GPU.
    let gpu = &all[&("Deployment".to_string(), "nephele-worker-gpu".to_string())];
    let limits = gpu.pointer("/spec/template/spec/containers/0/resources/limits/nvidia.com~1gpu");
    assert!(limits.is_some(), "the GPU workers must request nvidia.com/gpu");

    // The autoscaler scales a Deployment on metrics the master exports.
    let metrics_source =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../master/src/metrics.rs"))
            .expect("master/src/metrics.rs");
    let hpas: Vec<&Value> = all.iter().filter(|((k, _), _)| k == "HorizontalPodAutoscaler").map(|(_, d)| d).collect();
    assert!(!hpas.is_empty(), "no HorizontalPodAutoscaler");
    for hpa in hpas {
        let target = str_at(hpa, "/spec/scaleTargetRef/name").expect("scaleTargetRef");
        assert!(named("Deployment", target), "the autoscaler scales unknown {target}");
        for metric in items(hpa, "/spec/metrics") {
            let object = &metric["object"];
            let service = str_at(object, "/describedObject/name").expect("Object metric on a Service");
            assert!(named("Service", service), "the autoscaler reads unknown Service {service}");
            let name = str_at(object, "/metric/name").expect("metric name");
            let short = name.strip_prefix("nephele_master_").expect("a master metric");
            assert!(metrics_source.contains(&format!("\"{short}\"")), "the master exports no metric {name}");
        }
    }
}

/// `nephele [ROLE] --help`, asked once per role for all the command lines checked.
fn help_of(role: Option<&str>) -> String {
    static HELP: Mutex<BTreeMap<String, String>> = Mutex::new(BTreeMap::new());
    let mut cache = HELP.lock().unwrap_or_else(|p| p.into_inner());
    let key = role.unwrap_or("").to_string();
    cache
        .entry(key)
        .or_insert_with(|| {
            let args: Vec<&str> = role.into_iter().chain(["--help"]).collect();
            String::from_utf8_lossy(&nephele(&args).stdout).into_owned()
        })
        .clone()
}

/// Every `--flag` of a `nephele` command line is one its subcommand's `--help` lists.
fn check_flags(what: &str, args: &[&str]) {
    const ROLES: [&str; 7] = ["master", "composer", "worker", "up", "loadgen", "probe", "secret"];
    let Some(role_at) = args.iter().position(|a| ROLES.contains(a)) else {
        panic!("{what}: no nephele role in {args:?}")
    };
    let (global, role) = (help_of(None), help_of(Some(args[role_at])));
    for (i, flag) in args.iter().enumerate().filter(|(_, a)| a.starts_with("--")) {
        let help = if i < role_at { &global } else { &role };
        assert!(
            help.contains(&format!("{flag} ")) || help.contains(&format!("{flag}\n")),
            "{what}: nephele {} has no {flag}",
            if i < role_at { "" } else { args[role_at] }
        );
    }
}

#[test]
fn the_compose_file_runs_real_commands_on_a_private_network() {
    let compose = load(&deploy_dir().join("docker-compose.yml")).remove(0);
    let services = compose["services"].as_object().expect("services");
    for role in ["bake", "master", "composer", "worker"] {
        assert!(services.contains_key(role), "no {role} service");
    }
    for (name, service) in services {
        // Variables the file substitutes (`${NAME:-default}`) take their defaults here.
        let args: Vec<String> = items(service, "/command")
            .iter()
            .filter_map(|a| a.as_str())
            .map(|a| match a.split_once("${") {
                Some((_, rest)) => rest.split_once(":-").map_or("", |(_, d)| d.trim_end_matches('}')).to_string(),
                None => a.to_string(),
            })
            .collect();
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        check_flags(&format!("compose service {name}"), &args);
        assert_eq!(items(service, "/networks").len(), 1, "{name}: on the private network");
        assert!(service["image"].as_str().is_some_and(|i| i.contains("nephele")), "{name}: image");
    }
    // Only the web client (master) and the composer's WebRTC ports reach the host.
    let published: Vec<&str> =
        services.iter().filter(|(_, s)| s.get("ports").is_some()).map(|(n, _)| n.as_str()).collect();
    assert_eq!(published, ["composer", "master"]);
    assert_eq!(services["worker"]["scale"], 3, "three workers by default");
    assert!(services["worker"]["restart"].as_str().is_some_and(|r| r != "no"), "workers restart");
    // The farm is authenticated: every farm process reads the secret the one-shot job writes.
    for role in ["master", "composer", "worker"] {
        let env = &services[role]["environment"];
        assert_eq!(env["NEPHELE_FARM_SECRET_FILE"], "/var/lib/nephele/secrets/farm", "{role}: farm secret");
        assert!(
            items(&services[role], "/volumes")
                .iter()
                .any(|v| v.as_str() == Some("secrets:/var/lib/nephele/secrets:ro")),
            "{role}: the secret volume, read-only"
        );
        assert_eq!(services[role]["depends_on"]["secret"]["condition"], "service_completed_successfully", "{role}");
    }
    // The operators' endpoints need the token that another one-shot job writes in that
    // volume before the master (and so everything that waits for the master) starts.
    let token = services["master"]["environment"]["NEPHELE_OPERATOR_TOKEN_FILE"].as_str().expect("the master's token");
    for role in ["composer", "worker"] {
        assert_eq!(services[role]["environment"]["NEPHELE_OPERATOR_TOKEN_FILE"], token, "{role}: operators' token");
        assert_eq!(services[role]["depends_on"]["master"]["condition"], "service_started", "{role}");
    }
    let (writer, _) = services
        .iter()
        .find(|(_, s)| {
            let command: Vec<&str> = items(s, "/command").iter().filter_map(|a| a.as_str()).collect();
            command.starts_with(&["secret", "--out", token])
        })
        .unwrap_or_else(|| panic!("no one-shot service writes {token}"));
    assert_eq!(services["master"]["depends_on"][writer]["condition"], "service_completed_successfully");
    // The farm's links are TLS: every farm process reads the farm certificate folder that a
    // one-shot job writes there, and waits for it.
    let (tls_writer, tls_service) = services
        .iter()
        .find(|(_, s)| items(s, "/command").iter().any(|a| a.as_str() == Some("--farm-tls")))
        .expect("a one-shot service writes the farm certificate");
    let command: Vec<&str> = items(tls_service, "/command").iter().filter_map(|a| a.as_str()).collect();
    let out = command.iter().position(|a| *a == "--out").map(|i| command[i + 1]).expect("--out");
    for role in ["master", "composer", "worker"] {
        assert_eq!(services[role]["environment"]["NEPHELE_FARM_TLS_DIR"], out, "{role}: farm TLS folder");
        assert_eq!(
            services[role]["depends_on"][tls_writer]["condition"], "service_completed_successfully",
            "{role} waits for the farm certificate"
        );
    }
}
