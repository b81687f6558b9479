#!/bin/sh
# A CA, a server certificate for 127.0.0.1/localhost and one client certificate per robot (common
# name = robot id), for docs/security/*-mtls.json5. For trials only: in a fleet, keep the CA key
# offline and give each robot only its own key. Keys written here are never committed (certs/.gitignore).
#   sh docs/security/make-certs.sh [OUT_DIR (default docs/security/certs)] [ROBOT ...(default a b)]
set -eu
out=${1:-docs/security/certs}
[ $# -gt 0 ] && shift
robots=${*:-a b}
mkdir -p "$out"
cd "$out"
ec="-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes"
openssl req -x509 $ec -keyout ca.key -out ca.pem -days 365 -subj "/CN=gmmap fleet CA" 2>/dev/null
# rustls (Zenoh's TLS) takes only X.509 v3 certificates: every certificate gets extensions.
sign() {  # NAME CN EXTENSIONS
    openssl req $ec -keyout "$1.key" -out "$1.csr" -subj "/CN=$2" 2>/dev/null
    printf '%b' "$3" > "$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days 365 \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm "$1.csr" "$1.ext"
}
sign server gmmap-server "subjectAltName=IP:127.0.0.1,DNS:localhost\nextendedKeyUsage=serverAuth\n"
for robot in $robots; do
    sign "robot-$robot" "$robot" "subjectAltName=DNS:$robot\nextendedKeyUsage=clientAuth\n"
done
chmod 600 ./*.key
echo "wrote $(pwd): ca.pem, server.pem/.key, robot-<id>.pem/.key for: $robots"
