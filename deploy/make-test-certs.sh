#!/usr/bin/env bash
# Make a TEST certificate authority and the identities of deploy/zenoh/secure*.json5 (openssl only, offline).
#
#   deploy/make-test-certs.sh OUT_DIR [EXTRA_SAN ...]
#
# OUT_DIR gets ca.pem (the root every node trusts) and, per identity, NAME.pem + NAME.key (PKCS#8, mode 600):
#   rsucal-daemon     the daemon: the only identity that may publish/serve calibrations (subject "daemon")
#   rsucal-router     the Zenoh router of deploy/compose.yaml (server name "router")
#   vehicle-4242      calibration vehicle 4242: may publish only v2x/cam/4242 (ACL subject "vehicle/4242")
#   detector-sil-west the detector of RSU sil-west: may publish only its cameras' detections and images
#   rsucal-operator   an operator's client: may query status/calibration and trigger jobs
#   untrusted-client  signed by the same CA but in no ACL list: may only read (used by the tests)
# The certificate's common name (CN) is the identity the access control matches. Server certificates carry
# SANs localhost and 127.0.0.1 (plus "router" for the router) because Zenoh checks the name it connects to;
# EXTRA_SAN adds more to rsucal-daemon and rsucal-router, e.g. DNS:rsu-042.example.net or IP:10.0.0.5.
# DAYS (default 365) sets the validity. For production use your PKI; never ship ca.key onto an RSU.
set -euo pipefail

if [ $# -lt 1 ] || [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then
  sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'
  exit 2
fi
out=$1
shift
days=${DAYS:-365}
extra_sans=""
for san in "$@"; do
  case "$san" in
    DNS:* | IP:*) extra_sans="$extra_sans,$san" ;;
    *) echo "make-test-certs: EXTRA_SAN must start with DNS: or IP:, got '$san'" >&2; exit 2 ;;
  esac
done

mkdir -p "$out"
umask 077
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

new_key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# The CA: basicConstraints CA:TRUE is what rustls/webpki require of an issuer.
new_key "$out/ca.key"
openssl req -x509 -new -key "$out/ca.key" -sha256 -days "$days" -subj "/O=rsucal test/CN=rsucal test CA" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
  -addext "subjectKeyIdentifier=hash" -out "$out/ca.pem"

# issue NAME SANS: a leaf usable both to listen (serverAuth) and to connect with mutual TLS (clientAuth).
issue() {
  local name=$1 sans=$2
  new_key "$out/$name.key"
  openssl req -new -key "$out/$name.key" -subj "/O=rsucal test/CN=$name" -out "$tmp/$name.csr"
  cat >"$tmp/$name.ext" <<EXT
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectKeyIdentifier=hash
authorityKeyIdentifier=keyid
subjectAltName=$sans
EXT
  openssl x509 -req -in "$tmp/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
    -CAserial "$tmp/ca.srl" -sha256 -days "$days" -extfile "$tmp/$name.ext" -out "$out/$name.pem" 2>/dev/null
}

issue rsucal-daemon "DNS:rsucal-daemon,DNS:localhost,IP:127.0.0.1$extra_sans"
issue rsucal-router "DNS:router,DNS:rsucal-router,DNS:localhost,IP:127.0.0.1$extra_sans"
issue vehicle-4242 "DNS:vehicle-4242"
issue detector-sil-west "DNS:detector-sil-west"
issue rsucal-operator "DNS:rsucal-operator"
issue untrusted-client "DNS:untrusted-client"

chmod 644 "$out"/*.pem
chmod 600 "$out"/*.key
echo "make-test-certs: wrote $out/ca.pem and rsucal-daemon, rsucal-router, vehicle-4242, detector-sil-west," \
  "rsucal-operator, untrusted-client (.pem + .key), valid $days days"
