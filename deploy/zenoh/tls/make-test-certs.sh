#!/bin/sh
# Throwaway test PKI for Zenoh TLS / mTLS: a CA, a router (server) cert and a client cert.
#
#   deploy/zenoh/tls/make-test-certs.sh [OUT_DIR] [EXTRA_SAN]
#
# OUT_DIR defaults to ./certs. The router cert is valid for localhost and 127.0.0.1 (Zenoh checks
# the name in the connect endpoint against the SAN: verify_name_on_connect); for two hosts pass the
# router's address as EXTRA_SAN, e.g. "IP:192.168.1.10" or "DNS:router.lab".
# Writes ca.pem, ca.key, router.pem, router.key, client.pem, client.key (EC P-256, 30 days).
# For testing only: real deployments keep the CA key offline and never copy private keys around.
set -eu

out=${1:-certs}
extra=${2:-}
san="DNS:localhost,IP:127.0.0.1"
[ -n "$extra" ] && san="$san,$extra"
days=30

command -v openssl >/dev/null 2>&1 || { echo "make-test-certs.sh: openssl not found" >&2; exit 1; }
mkdir -p "$out"
cd "$out"
umask 077

# rustls (Zenoh's TLS) wants X.509 v3: a CA flagged CA:TRUE and leaves that are not CAs.
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout ca.key -out ca.pem \
    -days "$days" -subj "/CN=teleop test CA" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
    2>/dev/null

leaf() {  # leaf NAME CN EKU SAN
    cat >"$1.ext" <<EXT
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=$3
subjectAltName=$4
EXT
    openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout "$1.key" \
        -out "$1.csr" -subj "/CN=$2" 2>/dev/null
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days "$days" \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}

leaf router "teleop router" serverAuth "$san"
leaf client "teleop client" clientAuth "DNS:teleop-client"
rm -f ca.srl
chmod 644 ca.pem router.pem client.pem
echo "wrote $(pwd): ca.pem router.pem router.key client.pem client.key (+ ca.key)"
